"""Compiled builds of the hot pure-Python modules (mypyc): built by ``make native``, used if fresh.

The sources stay the only truth (README.md, "Using it"): a package that calls ``use_native`` loads
the build only while its stamp matches the sources; ``library`` loads the C libraries of
``LIBRARIES``. ``python tools/native.py build`` builds, ``status`` says what loads.
"""

from __future__ import annotations

import argparse
import ctypes
import fcntl
import hashlib
import importlib
import json
import logging
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
from functools import lru_cache
from pathlib import Path

from fabric.settings import env_name, settings

log = logging.getLogger(__name__)

# The directory holding the top-level packages (the repository, or site-packages when installed).
ROOT = Path(__file__).resolve().parents[1]
# Modules compiled together, as paths under ROOT. Every package holding one calls use_native in
# its __init__. A compiled class cannot be subclassed by interpreted code, so a module that
# subclasses one of these (netsim.simple subclasses netsim.radio_cell.RadioCell) is compiled with it.
MODULES = (
    "netsim/radio_cell.py",
    "netsim/simple.py",
    "netsim/nr/arrivals.py",
    "netsim/nr/buffers.py",
    "netsim/nr/counters.py",
    "netsim/nr/csi.py",
    "netsim/nr/downlink.py",
    "netsim/nr/draws.py",
    "netsim/nr/gnb_cell.py",
    "netsim/nr/link_fading.py",
    "netsim/nr/multicell.py",
    "netsim/nr/outcomes.py",
    "netsim/nr/radio_cell.py",
    "netsim/nr/channel.py",
    "netsim/nr/harq.py",
    "netsim/nr/uplink.py",
    "netsim/nr/link_adaptation.py",
    "netsim/nr/phy.py",
    "netsim/nr/scheduler.py",
    "netsim/records.py",
)
# Shared libraries built from C sources, by name (loaded with ``library``): code that must run
# with no GIL at all, which mypyc cannot give.
LIBRARIES = {"cosim5g_stepper": "services/physics/native_stepper.c"}
# Modules the compiled ones import: mypyc builds in the types it reads there, so an edit to them
# makes a build stale too.
DEPENDS = ("scenario/nr.py", "fabric/seeding.py")
GROUP = "cosim5g_native"  # mypyc's shared library of the group: cosim5g_native__mypyc
PURE_ENV = env_name("pure_python")
DIR_ENV = env_name("native_dir")


def native_dir() -> Path:
    """Where the build for this interpreter lives: ``COSIM5G_NATIVE_DIR``, else
    ``build/native/<cache tag>`` beside the packages."""
    return settings().native_dir or ROOT / "build" / "native" / sys.implementation.cache_tag


@lru_cache(maxsize=1)
def sources_digest() -> str:
    """The hex sha256 over the names and contents of the compiled modules, those they import and
    the C sources, and the interpreter's cache tag: what a build is stamped with."""
    h = hashlib.sha256(sys.implementation.cache_tag.encode())
    for rel in MODULES + DEPENDS + tuple(LIBRARIES.values()):
        h.update(b"\0" + rel.encode() + b"\0")
        h.update((ROOT / rel).read_bytes())
    return h.hexdigest()


def _stamped_digest(d: Path) -> str | None:
    """The source digest the build in ``d`` was stamped with (None: no build there)."""
    try:
        digest = json.loads((d / "stamp.json").read_text()).get("digest")
    except (OSError, ValueError):
        return None
    return digest if isinstance(digest, str) else None


def _module_name(rel: str) -> str:
    return rel[:-3].replace("/", ".")


@lru_cache(maxsize=1)
def _fresh_build() -> Path | None:
    """The build directory if it exists and was made from the sources as they are now."""
    if settings().pure_python:
        return None
    d = native_dir()
    stamped = _stamped_digest(d)
    if stamped is None:
        return None  # never built here: pure Python, nothing to say
    if stamped != sources_digest():
        log.warning("compiled modules in %s were built from other sources: running %s as pure "
                    "Python (make native rebuilds them)", d, ", ".join(MODULES))
        return None
    if str(d) not in sys.path:  # for the group's shared library, imported by every module
        sys.path.append(str(d))
    try:  # the group's code: it loads here, or no module of the build is used
        importlib.import_module(f"{GROUP}__mypyc")
    except ImportError as exc:
        log.warning("compiled modules in %s do not load (%s): running them as pure Python", d, exc)
        sys.path.remove(str(d))
        return None
    return d


def use_native(package: str, path: list[str]) -> None:
    """Called by a package's ``__init__`` with its ``__name__`` (``package``) and ``__path__``
    (``path``, changed in place): its compiled modules come first where a fresh build exists;
    its other modules load from source."""
    d = _fresh_build()
    if d is None:
        return
    sub = d.joinpath(*package.split("."))
    if sub.is_dir() and str(sub) not in path:
        path.insert(0, str(sub))


def library(name: str) -> ctypes.CDLL | None:
    """The shared library ``name`` of LIBRARIES from a fresh build, as a ``ctypes.CDLL`` (None: no
    fresh build, or the library does not load there; the caller runs its pure-Python way then)."""
    d = _fresh_build()
    if d is None:
        return None
    try:
        return ctypes.CDLL(str(d / f"lib{name}.so"))
    except OSError as exc:
        log.warning("library %s in %s does not load (%s)", name, d, exc)
        return None


def compiled_loaded() -> list[str]:
    """The dotted names of the modules of MODULES imported so far from the compiled build."""
    names = [_module_name(rel) for rel in MODULES]
    return [n for n in names if n in sys.modules
            and not (getattr(sys.modules[n], "__file__", None) or ".py").endswith(".py")]


def _loads(d: Path) -> bool:
    """True if the build in ``d`` loads in a fresh interpreter like this one."""
    probe = subprocess.run([sys.executable, "-c", f"import {GROUP}__mypyc"], env=dict(
        os.environ, PYTHONPATH=str(d)), capture_output=True, timeout=60)
    return probe.returncode == 0


def build(out: Path) -> str:
    """Compile MODULES and LIBRARIES into the directory ``out`` (replaced whole once the build
    succeeded); returns a line saying what was done. One build at a time per directory (a lock
    beside it); RuntimeError when the sources changed during the build."""
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out.parent / f".{out.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        return _build_locked(out)


def _build_locked(out: Path) -> str:
    digest = sources_digest()
    if _stamped_digest(out) == digest and _loads(out):
        return f"compiled modules up to date in {out}"
    # Imported here: mypyc and setuptools are build tools, absent from the runtime image.
    from mypyc.build import mypycify
    from setuptools import setup

    with tempfile.TemporaryDirectory(prefix="native-", dir=out.parent) as tmp:
        staging = Path(tmp) / "lib"
        cwd = os.getcwd()
        try:
            os.chdir(ROOT)  # mypyc names modules by their paths from here
            extensions = mypycify(list(MODULES), opt_level="3", group_name=GROUP,
                                  target_dir=str(Path(tmp) / "c"))
            os.chdir(tmp)  # away from the project's pyproject.toml, which is not this build's
            setup(name=GROUP, ext_modules=extensions, script_args=[
                "--quiet", "build_ext", "--build-lib", str(staging),
                "--build-temp", str(Path(tmp) / "obj")])
        finally:
            os.chdir(cwd)
        for name, rel in LIBRARIES.items():
            _compile_library(ROOT / rel, staging / f"lib{name}.so")
        sources_digest.cache_clear()
        if sources_digest() != digest:
            raise RuntimeError("sources changed during the build; run it again")
        (staging / "stamp.json").write_text(json.dumps(
            {"digest": digest, "modules": list(MODULES)}, indent=1) + "\n")
        if out.exists():
            shutil.rmtree(out)
        staging.rename(out)
    return f"compiled {len(MODULES)} modules and {len(LIBRARIES)} library into {out}"


def _compile_library(source: Path, out: Path) -> None:
    """A shared library from one C file, with the compiler that builds Python's extensions."""
    cc = (sysconfig.get_config_var("CC") or "cc").split()
    subprocess.run([*cc, "-O2", "-shared", "-fPIC", "-pthread", str(source), "-o", str(out)], check=True)


def main(argv: list[str] | None = None) -> int:
    """``build`` or ``status`` from ``argv`` (default: the command line); the exit code, 1 when
    the build failed (pure Python still runs)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("command", choices=("build", "status"))
    args = parser.parse_args(argv)
    if args.command == "build":
        try:
            print(build(native_dir()))
        # A missing compiler or header (setuptools and mypyc exit through SystemExit): pure
        # Python still runs.
        except (Exception, SystemExit) as exc:
            print(f"compiled modules not built ({type(exc).__name__}: {exc}); {', '.join(MODULES)} "
                  "run as pure Python, at about half the speed. The build needs mypy (in .venv), "
                  "gcc and the Python headers (Debian: apt-get install gcc python3-dev)",
                  file=sys.stderr)
            return 1
        return 0
    for rel in MODULES:  # each imported as the federates would
        importlib.import_module(_module_name(rel))
    loaded = compiled_loaded()
    libs = [name for name in LIBRARIES if library(name) is not None]
    print(f"{len(loaded)} of {len(MODULES)} modules compiled, {len(libs)} of {len(LIBRARIES)} "
          f"libraries ({native_dir()})")
    return 0
