"""Fixtures of the docker tests: a daemon client and the runtime image, or a clean skip."""

from __future__ import annotations

import gc
import uuid
import warnings
from collections.abc import Iterator
from typing import Any

import pytest

docker = pytest.importorskip("docker", reason="the docker SDK is not installed (pip install .[api])")

from coordinator.docker_runs import LABEL_RUN  # noqa: E402
from coordinator.runtime_docker import RUNTIME_IMAGE  # noqa: E402


def _connect() -> tuple[Any, str]:
    try:
        client = docker.from_env(timeout=10)
        client.ping()
    except Exception as e:  # any failure to talk to the daemon means: no docker here
        return None, str(e)
    return client, ""


@pytest.fixture(scope="session")
def docker_client() -> Iterator[Any]:
    """A client of a daemon that answers and has the runtime image; otherwise skip."""
    with warnings.catch_warnings():
        # A failed connection attempt leaves the SDK's socket to the garbage collector; collect
        # it here, where its ResourceWarning is not turned into an error by filterwarnings.
        warnings.simplefilter("ignore", ResourceWarning)
        client, error = _connect()
        gc.collect()
    if client is None:
        pytest.skip(f"Docker daemon not answering: {error}")
    try:
        client.images.get(RUNTIME_IMAGE)
    except docker.errors.ImageNotFound:
        client.close()
        pytest.skip(f"image {RUNTIME_IMAGE} missing: run `make images`")
    yield client
    client.close()


@pytest.fixture
def run_id(docker_client: Any) -> Iterator[str]:
    """A fresh run id; whatever a test leaves labelled with it is removed afterwards."""
    rid = f"test-{uuid.uuid4().hex[:8]}"
    yield rid
    selector = {"label": f"{LABEL_RUN}={rid}"}
    for c in docker_client.containers.list(all=True, filters=selector):
        c.remove(force=True)
    for n in docker_client.networks.list(filters=selector):
        n.remove()
