"""Points as Ray tasks, for sweeps over a cluster of machines (docs/architecture.md sec. 8).

Each point is one ``cosim5g run`` process, as with the local executor (same scenario and seed,
same results), whose run directory comes back packed. ``address``: ``auto`` or ``HOST:PORT``
joins a running cluster, None starts one on this machine for the sweep (README.md, "Sweeps").
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import shutil
import tarfile
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from coordinator.run_state import RunState
from coordinator.runtime_ray import check_reachable, no_usage_stats, short_error
from experiments.point_runs import PointOutcome, PointTask, run_process

log = logging.getLogger(__name__)


POINT_DIR_PREFIX = "cosim5g-point-"


def remove_stale_point_dirs() -> None:
    """Remove the point directories whose worker is gone: a point cancelled by force (the
    sweep's cancel) or lost with its worker never reaches its own clean-up."""
    for path in Path(tempfile.gettempdir()).glob(f"{POINT_DIR_PREFIX}*"):
        try:
            os.kill(int((path / "owner").read_text()), 0)
        except ProcessLookupError:
            shutil.rmtree(path, ignore_errors=True)
        except (OSError, ValueError):  # being made, or not this user's
            continue


def run_remote(config_yaml: str, run_id: str) -> dict[str, Any]:
    """On a Ray worker: run the point and return its state, KPIs and the packed run directory."""
    remove_stale_point_dirs()
    tmp = Path(tempfile.mkdtemp(prefix=POINT_DIR_PREFIX))
    (tmp / "owner").write_text(str(os.getpid()))
    try:
        config = tmp / "config.yaml"
        config.write_text(config_yaml)
        runs = tmp / "runs"
        t0 = time.monotonic()
        status, reason, kpis = run_process(config, runs, run_id, runs / f"{run_id}.log")
        wall = time.monotonic() - t0
        buf = io.BytesIO()
        with tarfile.open(fileobj=buf, mode="w:gz") as tar:
            for path in sorted(runs.iterdir()):
                tar.add(path, arcname=path.name)
        return {"status": status, "reason": reason, "kpis": kpis, "wall_s": wall, "archive": buf.getvalue()}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


class RayExecutor:
    name = "ray"

    def __init__(self, address: str | None = None, jobs: int | None = None, cpus_per_point: float = 1.0) -> None:
        try:
            import ray  # noqa: F401
        except ImportError:
            raise ImportError("the ray executor needs Ray: pip install -e '.[ray]'") from None
        if jobs is not None and jobs < 1:
            raise ValueError(f"jobs must be >= 1, got {jobs}")
        self.address = address
        self.jobs = jobs
        self.cpus_per_point = cpus_per_point

    @contextlib.contextmanager
    def session(self) -> Iterator[None]:
        """Ray up for the block (joined, or a local cluster started and stopped here): a sweep
        that runs in waves (``capacity.stop_after``) starts it once, not per wave."""
        import ray

        started_here = not ray.is_initialized()
        if started_here:
            if self.address:
                check_reachable(self.address)
                ray.init(address=self.address, log_to_driver=False)
            else:
                no_usage_stats()
                ray.init(include_dashboard=False, log_to_driver=False)
        try:
            yield
        finally:
            if started_here:
                ray.shutdown()

    def run(self, tasks: list[PointTask], on_start: Callable[[PointTask], None],
            on_done: Callable[[PointTask, PointOutcome], None], cancel: threading.Event) -> None:
        import ray

        with self.session():
            cpus = float(ray.cluster_resources().get("CPU", 0.0))
            if cpus < self.cpus_per_point:
                # The points wait for a node with CPUs: one an autoscaler adds, or none ever.
                log.warning("the Ray cluster offers %g CPUs and a point needs %g: the points wait for a "
                            "node with CPUs (ray start --num-cpus N on one, or cancel the sweep)",
                            cpus, self.cpus_per_point)
            cpus = max(cpus, self.cpus_per_point)
            limit = self.jobs or max(1, int(cpus // self.cpus_per_point))
            remote = ray.remote(num_cpus=self.cpus_per_point, max_retries=0)(run_remote)
            queue = list(tasks)
            pending: dict[Any, tuple[PointTask, float]] = {}
            requeued: set[str] = set()  # points given back to the queue after a lost worker or node
            lost = (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError, ray.exceptions.ObjectLostError)
            while (queue or pending) and not cancel.is_set():
                while queue and len(pending) < limit:
                    task = queue.pop(0)
                    if task.run_id not in requeued:
                        on_start(task)
                    ref = remote.remote(task.config_path.read_text(), task.run_id)
                    pending[ref] = (task, time.monotonic())
                ready, _ = ray.wait(list(pending), num_returns=1, timeout=0.5)
                for ref in ready:
                    task, t0 = pending.pop(ref)
                    try:
                        res = ray.get(ref)
                    except lost as exc:
                        # The cluster failed, not the point: run it again, once, wherever Ray
                        # places it now; a second loss fails it.
                        if task.run_id not in requeued:
                            requeued.add(task.run_id)
                            log.warning("point %s: %s; back to the queue once", task.run_id, short_error(exc))
                            queue.insert(0, task)
                            continue
                        on_done(task, self._failed(task, t0, f"ray task lost twice: {short_error(exc)}"))
                        continue
                    except Exception as exc:  # the point's own failure: the sweep goes on
                        on_done(task, self._failed(task, t0, f"ray task failed: {exc}"))
                        continue
                    on_done(task, self._outcome(res, task))
            for ref in pending:  # cancelled: the points in flight are rerun on resume
                ray.cancel(ref, force=True)

    @staticmethod
    def _failed(task: PointTask, t0: float, reason: str) -> PointOutcome:
        return PointOutcome(task.point.key, task.run_id, RunState.FAILED, reason[:2000],
                            task.runs_dir / task.run_id, time.monotonic() - t0)

    @staticmethod
    def _outcome(res: dict[str, Any], task: PointTask) -> PointOutcome:
        run_dir = task.runs_dir / task.run_id
        task.runs_dir.mkdir(parents=True, exist_ok=True)
        with tarfile.open(fileobj=io.BytesIO(res["archive"]), mode="r:gz") as tar:
            tar.extractall(task.runs_dir, filter="data")
        # The run directory recorded the worker's path; point it at where the sweep keeps it.
        kpis = {**res["kpis"], "results_dir": str(run_dir)} if res["kpis"] else {}
        return PointOutcome(task.point.key, task.run_id, res["status"], res["reason"], run_dir, res["wall_s"], kpis)

