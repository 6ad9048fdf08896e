"""Integration tests talk to coordinators they start: one API token for all of them.

``cosim5g serve`` processes inherit ``COSIM5G_TOKEN`` and ``interfaces.client`` sends it, so no
test reads or writes the token file of the working folder (``results/auth/api-token``, which
``make up`` uses). Tests of the token file itself unset it."""

from __future__ import annotations

import secrets
from collections.abc import Iterator

import pytest


@pytest.fixture(scope="session", autouse=True)
def api_token() -> Iterator[str]:
    token = f"test-{secrets.token_urlsafe(24)}"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("COSIM5G_TOKEN", token)
        yield token
