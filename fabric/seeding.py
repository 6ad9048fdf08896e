"""Named random streams: one root seed per run, one independent stream per component name.

A stream depends only on (root seed, name), so adding a federate or starting federates in another
order changes no other stream.
"""

from __future__ import annotations

import hashlib

import numpy as np


def stream_seed(root_seed: int, name: str) -> np.random.SeedSequence:
    """The SeedSequence of the stream called ``name`` (e.g. ``camera-0/pdp``) under the run's
    ``root_seed`` (its low 32 bits), from a SHA-256 of the name."""
    digest = hashlib.sha256(name.encode()).digest()
    words = [int.from_bytes(digest[i : i + 4], "little") for i in range(0, 16, 4)]
    return np.random.SeedSequence([root_seed & 0xFFFFFFFF, *words])


def rng(root_seed: int, name: str) -> np.random.Generator:
    """A numpy Generator (PCG64) drawing the stream ``name`` of the run seeded ``root_seed``."""
    return np.random.Generator(np.random.PCG64(stream_seed(root_seed, name)))
