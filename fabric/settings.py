"""Every setting the platform takes from its environment: the ``COSIM5G_*`` variables, each a field
of ``Settings``, read through ``settings()`` and passed on to processes by ``env_name``.
A bad value fails naming the variable, the value and what is allowed.
"""

from __future__ import annotations

import os
from collections.abc import MutableMapping
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, ValidationError
from pydantic_settings import BaseSettings, SettingsConfigDict

PREFIX = "COSIM5G_"


class Settings(BaseSettings):
    # An empty variable is an unset one (``COSIM5G_HOST_SCORE= cmd``).
    model_config = SettingsConfigDict(env_prefix=PREFIX, extra="ignore", frozen=True, env_ignore_empty=True)

    # The REST API (interfaces.api, interfaces.auth, interfaces.client).
    token: str | None = Field(default=None, description="the API token (else the token file's)")
    token_file: Path | None = Field(default=None, description="the API token's file (default "
                                    "results/auth/api-token)")
    max_duration_s: float = Field(default=3600.0, gt=0, allow_inf_nan=False,
                                  description="longest simulated duration_s of a run or sweep point, s")
    max_run_timeout_s: float = Field(default=21600.0, gt=0, allow_inf_nan=False,
                                     description="largest watchdog.run_timeout_s (wall clock) of a run or "
                                     "sweep point, s")
    max_sweep_points: int = Field(default=1000, ge=1, description="most points (grid combinations x seeds, "
                                  "repeat_until's extra seeds included) in one sweep")
    max_queued: int = Field(default=32, ge=1, description="most runs and sweeps pending or running at once")
    max_body_bytes: int = Field(default=1_000_000, ge=1024, description="largest request body, bytes (413 "
                                "beyond it, before the body is read or the token checked)")
    slots: int = Field(default_factory=lambda: max(1, (os.cpu_count() or 2) // 2), ge=1,
                       description="runs and sweep points simulated at once (a run of many loops uses about "
                       "two cores)")
    # Compute and builds (fabric.native, fabric.host_speed, domain.frame_model).
    native_dir: Path | None = Field(default=None, description="where the native builds are (default "
                                    "build/native/<cache tag>)")
    pure_python: bool = Field(default=False, description="never use the native builds")
    host_score: float | None = Field(default=None, gt=0, allow_inf_nan=False,
                                     description="this host's speed score, instead of measuring it")
    cache_dir: Path | None = Field(default=None, description="cache of measured models (default "
                                   "~/.cache/cosim5g)")
    # A federate process (services.main, fabric.metrics), as its runtime starts it.
    metrics_port: int | None = Field(default=None, ge=1, le=65535, description="serve Prometheus metrics on it")
    parent_pid: int | None = Field(default=None, description="the coordinator's pid: the federate stops "
                                   "when that process is gone")
    profile_dir: Path | None = Field(default=None, description="write each federate's cProfile statistics here")
    # The docker runtime's coordinator (coordinator.runtime_docker).
    router_host: str | None = Field(default=None, description="the name containers reach the coordinator's "
                                    "zenoh router by")
    federate_metrics_port: int | None = Field(default=None, ge=1, le=65535,
                                              description="the port each federate container serves metrics on")
    # The ray runtime's coordinator (coordinator.runtime_ray).
    ray_address: str | None = Field(default=None, description="the Ray cluster a `runtime: ray` run joins: "
                                    "auto or HOST:PORT (default: start a local one for the run)")
    ray_router_host: str | None = Field(default=None, description="the address Ray nodes reach the "
                                        "coordinator's zenoh router at (default: the coordinator's Ray node "
                                        "address when joining a cluster, 127.0.0.1 for a local one)")
    ray_placement: Literal["PACK", "SPREAD", "STRICT_PACK", "STRICT_SPREAD"] = Field(
        default="PACK", description="the Ray placement strategy of a run's federate processes")
    ray_placement_timeout_s: float = Field(default=30.0, gt=0, allow_inf_nan=False,
                                           description="longest wait for Ray to place a run's federates, s")
    ray_records: Literal["auto", "stream"] = Field(
        default="auto", description="where a Ray node's federates write: auto, into the run directory "
        "where the node sees it (shared), else their table parts are streamed to the coordinator over "
        "zenoh as they are written and the rest (logs, files written at the end) is shipped back "
        "through Ray's object store when the run stops; stream: always the latter")


def settings(**given: Any) -> Settings:
    """The settings: each field from ``given`` (keyword = field name; None = not given), else
    from its ``COSIM5G_*`` variable, else its default. ValueError naming the variable, the value
    and what is allowed, for a bad value."""
    try:
        return Settings(**{k: v for k, v in given.items() if v is not None})
    except ValidationError as exc:
        raise ValueError("; ".join(f"{e['loc'][0]} ({env_name(str(e['loc'][0]))}) = {e['input']!r}: {e['msg']}"
                                   for e in exc.errors())) from None


def env_name(field: str) -> str:
    """The environment variable of the settings field ``field``: ``max_queued`` ->
    ``COSIM5G_MAX_QUEUED``."""
    return f"{PREFIX}{field.upper()}"


# The thread pools a simulation process runs with one thread each: a node's speed is emulated, and
# BLAS/OpenMP pools on a shared host only add noise to CPU-time measurements.
THREAD_POOL_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def one_thread_pools(env: MutableMapping[str, str]) -> None:
    """Give every pool of ``THREAD_POOL_VARS`` one thread in ``env`` where it names none."""
    for var in THREAD_POOL_VARS:
        env.setdefault(var, "1")
