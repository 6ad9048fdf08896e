"""Property-based fuzzing of the REST API from its own OpenAPI schema (schemathesis): whatever a
client sends, with the token, no answer is a server error and every documented answer matches
its schema; and an operation that declares the token refuses a request without it.

The app is the real one (routes, validation, limits, store), served in process; only the run and
sweep executors are stand-ins, so an accepted run ends at once instead of simulating."""

from __future__ import annotations

import atexit
import shutil
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

schemathesis = pytest.importorskip("schemathesis", reason="schemathesis is in the dev extra")

from hypothesis import HealthCheck, settings  # noqa: E402
from schemathesis.checks import not_a_server_error  # noqa: E402
from schemathesis.specs.openapi.checks import (  # noqa: E402
    ignored_auth,
    response_schema_conformance,
)

from coordinator.run import RunResult  # noqa: E402
from experiments.point_runs import PointTask  # noqa: E402
from fabric.settings import settings as platform_settings  # noqa: E402
from interfaces.api import create_app  # noqa: E402
from scenario.schema import Scenario  # noqa: E402

pytestmark = pytest.mark.integration
ROOT = Path(__file__).parents[2]
TOKEN = "fuzz-token-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def instant_run(sc: Scenario, results_root: Path, on_progress: Any = None,
                cancel: threading.Event | None = None, run_id: str | None = None) -> RunResult:
    assert run_id is not None
    return RunResult(run_id, "completed", results_root / run_id, {"sim_time_s": sc.duration_s})


class NoPoints:
    name = "none"

    def run(self, tasks: list[PointTask], on_start: Any, on_done: Any, cancel: threading.Event) -> None:
        del tasks, on_start, on_done, cancel


def build_app(root: Path) -> Any:
    # Small limits, so that the fuzzer meets them (422 and 429 answers) as well.
    return create_app(root / "runs", root / "store.db", ROOT / "configs" / "scenarios", root / "sweeps",
                      ROOT / "configs" / "sweeps", token=TOKEN, execute=instant_run,
                      make_sweep_executor=lambda slots: NoPoints(),
                      limits=platform_settings(max_duration_s=60, max_run_timeout_s=3600, max_sweep_points=50,
                                               max_queued=4))


# The schema is loaded when the module is (schemathesis generates one test per operation at
# collection), so the app is built then too, in a folder removed with the module's tests.
STATE = Path(tempfile.mkdtemp(prefix="cosim5g-fuzz-"))
atexit.register(shutil.rmtree, STATE, True)  # also when the module is collected but not run
APP = build_app(STATE)


async def without_lifespan(scope: dict[str, Any], receive: Any, send: Any) -> None:
    """The app, minus its lifespan: schemathesis ends an app's lifespan after each operation's
    test and starts it again, while the coordinator's store and workers live as long as the app
    (they are closed once, after the last test)."""
    if scope["type"] == "lifespan":
        return  # declining the scope says "no lifespan here"
    await APP(scope, receive, send)


# The live schema, fetched from the app itself, with the token like any client.
schema = schemathesis.openapi.from_asgi("/openapi.json", without_lifespan, headers=AUTH)


@pytest.fixture(scope="module", autouse=True)
def _close_app() -> Iterator[None]:
    yield
    APP.app.state.jobs.close()


@schema.parametrize()
@settings(max_examples=15, deadline=None, derandomize=True, database=None,
          suppress_health_check=list(HealthCheck))
def test_api_survives_fuzzing(case: Any) -> None:
    case.call_and_validate(headers=AUTH, checks=[not_a_server_error, response_schema_conformance, ignored_auth])
