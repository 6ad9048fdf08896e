"""The layers (docs/architecture.md sec. 11) hold: import-linter's contracts (pyproject.toml) pass, and they
cover every package of the project, so no new package can sit outside the picture unchecked."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).parents[2]


def _config() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_import_contracts_are_kept() -> None:
    lint = Path(sys.executable).with_name("lint-imports")
    proc = subprocess.run([str(lint)], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    assert "0 broken" in proc.stdout


def test_every_package_of_the_project_is_in_a_layer() -> None:
    cfg = _config()
    packages = set(cfg["tool"]["setuptools"]["packages"]["find"]["include"])
    roots = {p.rstrip("*") for p in packages}
    linter = cfg["tool"]["importlinter"]
    assert set(linter["root_packages"]) == roots
    layered = set()
    for contract in linter["contracts"]:
        if contract["type"] == "layers":
            for layer in contract["layers"]:
                layered |= {m.strip() for m in layer.replace("|", ":").split(":")}
    assert layered == roots
    # benchmarks/ are scripts run from a checkout (python -m benchmarks.x), not installed: they
    # may use any layer.
    on_disk = {p.parent.name for p in ROOT.glob("*/__init__.py")} - {"benchmarks"}
    assert on_disk == roots, "a top-level package that is not installed or not layered"


def test_federates_are_declared_independent() -> None:
    """Every package of services/ and netsim, by a wildcard: a new role's package is covered
    without an edit, and every registered role is served from a covered package."""
    from services.roles import ROLES

    contracts = [c for c in _config()["tool"]["importlinter"]["contracts"] if c["type"] == "independence"]
    assert len(contracts) == 1
    assert contracts[0]["modules"] == ["services.*", "netsim"]
    for role in ROLES.values():
        package = role.federate.split(":")[0].split(".")
        assert package[0] == "netsim" or (package[0] == "services" and len(package) > 2), role
