"""The compiled build of the NR cell (fabric.native): used only while it matches its sources and
loads, and computing exactly what the pure Python modules compute."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from fabric import native

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def fake_build(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A build directory with a stamp of the current sources and a group library that loads."""
    monkeypatch.setenv(native.DIR_ENV, str(tmp_path))
    monkeypatch.delenv(native.PURE_ENV, raising=False)
    # This process may run the real build: hide it while the fake one is looked at.
    real = str(native.ROOT / "build" / "native")
    monkeypatch.setattr(sys, "path", [p for p in sys.path if not p.startswith(real)])
    monkeypatch.delitem(sys.modules, f"{native.GROUP}__mypyc", raising=False)
    (tmp_path / "netsim" / "nr").mkdir(parents=True)
    (tmp_path / "stamp.json").write_text(json.dumps({"digest": native.sources_digest()}))
    (tmp_path / f"{native.GROUP}__mypyc.py").write_text("")
    native._fresh_build.cache_clear()
    yield tmp_path
    native._fresh_build.cache_clear()
    sys.modules.pop(f"{native.GROUP}__mypyc", None)


def test_a_fresh_build_comes_first_on_the_package_path(fake_build: Path) -> None:
    path = ["/src/netsim/nr"]
    native.use_native("netsim.nr", path)
    assert path == [str(fake_build / "netsim" / "nr"), "/src/netsim/nr"]
    native.use_native("netsim.nr", path)  # a second call adds nothing
    assert path == [str(fake_build / "netsim" / "nr"), "/src/netsim/nr"]


def test_a_build_of_other_sources_is_not_used(fake_build: Path, caplog: pytest.LogCaptureFixture) -> None:
    (fake_build / "stamp.json").write_text(json.dumps({"digest": "0" * 64}))
    path = ["/src/netsim"]
    native.use_native("netsim", path)
    assert path == ["/src/netsim"]
    assert "built from other sources" in caplog.text and "make native" in caplog.text


def test_a_build_that_does_not_load_is_not_used(fake_build: Path, caplog: pytest.LogCaptureFixture) -> None:
    (fake_build / f"{native.GROUP}__mypyc.py").write_text("raise ImportError('undefined symbol')")
    path = ["/src/netsim"]
    native.use_native("netsim", path)
    assert path == ["/src/netsim"]
    assert "undefined symbol" in caplog.text
    assert str(fake_build) not in sys.path


def test_pure_python_can_be_asked_for(fake_build: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(native.PURE_ENV, "1")
    path = ["/src/netsim"]
    native.use_native("netsim", path)
    assert path == ["/src/netsim"]


def test_no_build_means_pure_python_without_a_word(fake_build: Path, caplog: pytest.LogCaptureFixture) -> None:
    (fake_build / "stamp.json").unlink()
    path = ["/src/netsim"]
    native.use_native("netsim", path)
    assert path == ["/src/netsim"] and not caplog.text


def test_a_library_comes_from_a_fresh_build_only(fake_build: Path, caplog: pytest.LogCaptureFixture,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    assert native.library("cosim5g_stepper") is None  # in the build's stamp, not in its directory
    assert "does not load" in caplog.text
    real = native.ROOT / "build" / "native" / sys.implementation.cache_tag / "libcosim5g_stepper.so"
    if real.exists():
        (fake_build / real.name).write_bytes(real.read_bytes())
        assert native.library("cosim5g_stepper") is not None
    monkeypatch.setenv(native.PURE_ENV, "1")
    native._fresh_build.cache_clear()
    assert native.library("cosim5g_stepper") is None


STANDALONE = """
import json, sys
from fabric.native import compiled_loaded
from netsim.standalone import run_uplink_cameras
runs = [run_uplink_cameras(36, 8.5, 2.0, seed=3),
        run_uplink_cameras(24, 8.5, 1.0, seed=4, delay_budget_us=20_000)]
for r in runs:  # wall-clock figures differ from run to run
    for key in [k for k in r if "per_second" in k or k.endswith("_s")]:
        r.pop(key)
print(json.dumps(compiled_loaded()))
print(json.dumps(runs, sort_keys=True))
"""


def _standalone(pure: bool) -> tuple[list[str], str]:
    """The compiled modules the run used, and its results as JSON text (text: 1 and 1.0 differ)."""
    env = {k: v for k, v in os.environ.items() if k not in (native.PURE_ENV, native.DIR_ENV)}
    if pure:
        env[native.PURE_ENV] = "1"
    out = subprocess.run([sys.executable, "-c", STANDALONE], env=env, cwd=ROOT, capture_output=True,
                         text=True, timeout=300, check=True)
    compiled, runs = out.stdout.splitlines()[-2:]
    return json.loads(compiled), runs


def test_the_compiled_cell_computes_what_the_pure_one_does() -> None:
    modules, compiled = _standalone(pure=False)
    if not modules:
        if os.environ.get("CI"):
            pytest.fail("no compiled build of netsim in CI: `make native` failed (see its message)")
        pytest.skip("no compiled build (make native)")
    no_modules, pure = _standalone(pure=True)
    assert no_modules == []
    assert {"netsim.radio_cell", "netsim.nr.radio_cell", "netsim.nr.buffers", "netsim.nr.scheduler"} <= set(modules)
    assert compiled == pure
    saturated, budget = json.loads(compiled)
    assert saturated["lost_packets"]["buffer_overflow"] > 0  # full buffers
    assert budget["lost_packets"]["delay_budget"] > 0  # discards at the delay budget
