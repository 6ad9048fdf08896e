"""Uniform draws from one named random stream, fetched in blocks (scalar numpy draws are slow)."""

from __future__ import annotations

import numpy as np


class Uniforms:
    """Calling it returns the next uniform draw in [0, 1) of ``gen``, the same sequence as
    ``gen.random()`` called once per draw."""

    __slots__ = ("_gen", "_buf", "_i")

    def __init__(self, gen: np.random.Generator) -> None:
        self._gen = gen
        self._buf: list[float] = []
        self._i = 0

    def __call__(self) -> float:
        i = self._i
        if i == len(self._buf):
            self._buf = self._gen.random(4096).tolist()
            i = 0
        self._i = i + 1
        return self._buf[i]
