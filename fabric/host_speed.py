"""Host speed in reference cores: the scoring workload, this host's cached score and the reference.

What a score is, where it comes from and how durations are scaled: docs/compute.md, "What cpus
means: reference cores". ``python tools/host_speed.py`` prints this host's score
(``--write-cache`` caches it; ``--write-reference`` records the reference core: a quiet host).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import sys
import time
import zlib
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime, timedelta
from functools import cache
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from fabric.settings import env_name, settings

# Bump when the scoring workload changes: scores of different versions are not comparable.
SCORE_VERSION = 1
SCORE_ENV = env_name("host_score")
CACHE_MAX_AGE_DAYS = 7
# A cached score further than this factor from the reference core's is no measurement of a real host.
PLAUSIBLE_SPREAD = 50.0
REFERENCE_FILE = "data/reference_core.json"
# Repetitions of the whole mix: the full measurement (start of a node, cache miss) and the short
# probe a node takes during a run to see whether its speed drifted.
MEASURE_REPS = 15
PROBE_REPS = 3
# A measurement during which other processes kept more than this many cores busy is not cached.
BUSY_CORES_LIMIT = 0.25


class _Inputs:
    """The scoring workload's fixed inputs, built once per process (building is not timed)."""

    def __init__(self) -> None:
        gen = np.random.default_rng(20240601)
        # A smooth image with texture, like a rendered frame: JPEG cost depends on content.
        y, x = np.mgrid[0:240, 0:320].astype(np.float32)
        base = 128 + 60 * np.sin(x / 17.0)[..., None] * np.cos(y / 23.0)[..., None]
        noise = gen.normal(0, 6, (240, 320, 3))
        self.image = np.clip(base + noise, 0, 255).astype(np.uint8)
        self.float_image = self.image[..., 1].astype(np.float32) / 255.0
        self.kernel = gen.normal(0, 1, (5, 5)).astype(np.float32)
        depth = (900 + 40 * np.sin(x / 31.0) + gen.normal(0, 2, x.shape)).astype(np.uint16)
        self.depth_bytes = np.diff(depth, axis=1, prepend=0).astype(np.int16).tobytes()
        self.matrices = gen.normal(0, 1, (64, 6, 6))
        self.vectors = gen.normal(0, 1, (64, 6))


@cache
def _inputs() -> _Inputs:
    return _Inputs()


def _python() -> int:
    """Interpreted Python: integer arithmetic, a dict and a list, like controllers and policies."""
    acc, table = 0, {}
    for i in range(60_000):
        acc = (acc * 31 + i) % 1_000_003
        if i % 7 == 0:
            table[i % 101] = acc
    return acc + sum(table.values())


def _numpy() -> float:
    """Small-array numpy algebra (6x6 solves, norms, clips), like inverse kinematics and tracking."""
    inp = _inputs()
    acc = 0.0
    for _ in range(3):
        for a, b in zip(inp.matrices, inp.vectors, strict=True):
            x = np.linalg.solve(a @ a.T + np.eye(6), b)
            acc += float(np.linalg.norm(np.clip(x, -1.0, 1.0)))
    return acc


def _opencv() -> int:
    """OpenCV: a float 5x5 convolution (the estimator's kind of arithmetic) and a JPEG encode."""
    import cv2

    inp = _inputs()
    size = 0
    for _ in range(4):
        out = cv2.filter2D(inp.float_image, -1, inp.kernel)
        ok, jpg = cv2.imencode(".jpg", inp.image, [cv2.IMWRITE_JPEG_QUALITY, 84])
        if not ok:
            raise RuntimeError("OpenCV failed to encode the scoring image")
        size += int(out.shape[0]) + len(jpg)
    return size


def _zlib() -> int:
    """zlib at level 1 on delta-coded depth, like the camera's depth codec."""
    return len(zlib.compress(_inputs().depth_bytes, 1))


COMPONENTS = {"python": _python, "numpy": _numpy, "opencv": _opencv, "zlib": _zlib}


def run_mix() -> dict[str, float]:
    """One run of every component of the mix; returns each one's thread-CPU time, milliseconds."""
    out = {}
    for name, fn in COMPONENTS.items():
        t0 = time.thread_time_ns()
        fn()
        out[name] = (time.thread_time_ns() - t0) / 1e6
    return out


def measure_components(reps: int = MEASURE_REPS, fastest: bool = True) -> dict[str, float]:
    """Thread-CPU time per component over ``reps`` mixes (after one warm-up mix), milliseconds:
    the fastest run of each (``fastest``: the core's uncontended speed, since contention only ever
    slows a thread down) or the median (the speed jobs met in that moment).

    The pools of OpenCV stay at one thread: the score is one core's speed."""
    import cv2

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        run_mix()  # lazy imports, input construction, caches
        runs = [run_mix() for _ in range(max(1, reps))]
    finally:
        cv2.setNumThreads(threads)
    pick = min if fastest else statistics.median
    return {name: pick(r[name] for r in runs) for name in COMPONENTS}


def score_of(components_ms: dict[str, float]) -> float:
    """The score of ``components_ms`` (thread-CPU milliseconds per component): the geometric mean
    of their runs per CPU second."""
    logs = [math.log(1000.0 / max(ms, 1e-6)) for ms in components_ms.values()]
    return math.exp(sum(logs) / len(logs))


def cpu_model() -> str:
    """The host's CPU model name (``/proc/cpuinfo``), or the platform's processor string."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def environment() -> dict[str, str]:
    """What a score depends on, by name: the CPU model, the interpreter and library builds and the
    scoring workload's version."""
    import cv2

    return {
        "cpu_model": cpu_model(),
        "python": f"{platform.python_implementation()} {sys.version.split()[0]} ({platform.python_compiler()})",
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "score_version": str(SCORE_VERSION),
    }


@dataclass
class HostScore:
    """A host's measured speed: ``score`` (mix runs per CPU second) and how it was obtained."""

    score: float
    components_ms: dict[str, float] = field(default_factory=dict)
    source: str = "measured"  # measured, cache, injected
    measured_at: str = ""
    env: dict[str, str] = field(default_factory=dict)

    def component_ratios(self, ref: HostScore) -> dict[str, float]:
        """Per component, this host's speed over that of ``ref``, the reference core (>1:
        faster)."""
        return {k: ref.components_ms[k] / v for k, v in self.components_ms.items()
                if k in ref.components_ms and v > 0}


@cache
def reference() -> HostScore:
    """The reference core's score, recorded in the package data (read once a process)."""
    data = json.loads(resources.files("fabric").joinpath(REFERENCE_FILE).read_text())
    if int(data["env"].get("score_version", -1)) != SCORE_VERSION:
        raise RuntimeError(
            f"{REFERENCE_FILE} was measured with scoring workload version "
            f"{data['env'].get('score_version')}, this code runs version {SCORE_VERSION}: "
            "re-record it with python tools/host_speed.py --write-reference")
    return HostScore(score=float(data["score"]), components_ms=dict(data["components_ms"]),
                     source="reference", measured_at=str(data["measured_at"]), env=dict(data["env"]))


def cache_path() -> Path:
    """Where this host's score is cached: ``host_score.json`` in ``COSIM5G_CACHE_DIR`` (where the
    measured frame models are cached too), else in ``$XDG_CACHE_HOME/cosim5g`` (default
    ``~/.cache``)."""
    if (given := settings().cache_dir) is not None:
        return given / "host_score.json"
    root = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(root) / "cosim5g" / "host_score.json"


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


def _read_cache(path: Path, env: dict[str, str]) -> HostScore | None:
    try:
        data = json.loads(path.read_text())
        when = datetime.fromisoformat(data["measured_at"])
        age = datetime.now(UTC) - when
        score = float(data["score"])
        # Every job's duration is scaled by the score: one no measurement gives (not a positive
        # number, or far from any core's) or from the future would silently change every result.
        ref = reference().score
        if (data["env"] != env or not timedelta(minutes=-5) <= age <= timedelta(days=CACHE_MAX_AGE_DAYS)
                or not math.isfinite(score) or not ref / PLAUSIBLE_SPREAD <= score <= ref * PLAUSIBLE_SPREAD):
            return None
        return HostScore(score=score, components_ms=dict(data["components_ms"]),
                         source="cache", measured_at=data["measured_at"], env=dict(data["env"]))
    except (OSError, ValueError, KeyError, TypeError):
        return None  # no cache, another host's or a damaged one: measure again


def _write_atomic(path: Path, data: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    tmp.replace(path)


def injected_score() -> float | None:
    """The score given in ``COSIM5G_HOST_SCORE`` (None when unset); ValueError for one that is
    not a positive number."""
    return settings().host_score


def measure(reps: int = MEASURE_REPS) -> HostScore:
    """Measure this host's score now, each component's fastest of ``reps`` mixes (no cache)."""
    comps = measure_components(reps)
    return HostScore(score=score_of(comps), components_ms=comps, source="measured",
                     measured_at=_now(), env=environment())


@cache
def host_score() -> HostScore:
    """This host's score: injected, else cached, else measured now and cached (once a process)."""
    injected = injected_score()
    if injected is not None:
        return HostScore(score=injected, source="injected", measured_at=_now())
    env = environment()
    path = cache_path()
    cached = _read_cache(path, env)
    if cached is not None:
        return cached
    before = _host_cpu_s()
    own0, wall0 = time.process_time(), time.monotonic()
    fresh = measure()
    others = _others_busy_cores(before, _host_cpu_s(), time.process_time() - own0, time.monotonic() - wall0)
    if others is not None and others > BUSY_CORES_LIMIT:
        # Other work shared the host while it was measured (on a 2-core host, even one busy core
        # slows this one: shared caches, SMT siblings): good for this process, which runs under
        # the same contention, but not as this host's speed for the next week. Measured during
        # the measurement itself: the load average lags by a minute.
        fresh.source = f"measured (not cached: {others:.2f} other cores busy)"
        return fresh
    try:
        _write_atomic(path, asdict(fresh))
    except OSError:
        pass  # a read-only home (containers): the score is simply measured at every start
    return fresh


def _host_cpu_s() -> float | None:
    """CPU seconds the whole host has spent busy since boot (/proc/stat; None elsewhere)."""
    try:
        fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]
    except OSError:
        return None
    ticks = [int(v) for v in fields[:8]]  # user nice system idle iowait irq softirq steal
    busy = sum(ticks) - ticks[3] - ticks[4]
    return busy / os.sysconf("SC_CLK_TCK")


def _others_busy_cores(before: float | None, after: float | None, own_cpu_s: float,
                       wall_s: float) -> float | None:
    """Cores other processes kept busy on average while this one measured (None: unknown)."""
    if before is None or after is None or wall_s <= 0:
        return None
    return max(0.0, (after - before - own_cpu_s) / wall_s)


def probe() -> float:
    """A short measurement of the speed jobs meet now (the score of the median of ``PROBE_REPS``
    mixes, about 50 ms of CPU), for drift checks during a run."""
    return score_of(measure_components(PROBE_REPS, fastest=False))


def main(argv: list[str] | None = None) -> int:
    """Measure and print this host's score as JSON, with ``argv`` (default: the command line)
    saying whether to cache it or record it as the reference; the exit code."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=15, help="mixes to take each component's fastest of")
    ap.add_argument("--write-cache", action="store_true",
                    help="store the measurement as this host's cached score, however busy the host")
    ap.add_argument("--write-reference", action="store_true",
                    help=f"record this host as the reference core (fabric/{REFERENCE_FILE})")
    args = ap.parse_args(argv)
    host = measure(args.reps)
    out: dict[str, Any] = asdict(host)
    if args.write_reference:
        path = Path(__file__).parent / REFERENCE_FILE
        record = {k: out[k] for k in ("score", "components_ms", "measured_at", "env")}
        record["about"] = ("The reference core of node profiles' cpus: this host's score, measured "
                           "with python tools/host_speed.py --write-reference.")
        _write_atomic(path, record)
        print(f"reference core written to {path}")
    else:
        if args.write_cache:
            _write_atomic(cache_path(), out)
        try:
            ref = reference()
            out["reference_score"] = ref.score
            out["scale"] = host.score / ref.score
            out["component_ratios"] = host.component_ratios(ref)
        except (OSError, RuntimeError, KeyError) as exc:
            out["reference_error"] = str(exc)
    print(json.dumps(out, indent=2))
    return 0
