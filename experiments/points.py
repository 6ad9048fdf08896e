"""Points of a sweep: one resolved scenario and seed each, keyed by the hash of both.

The key is what makes a sweep resumable: a point whose key already completed is never run again,
whatever the order, the executor or the number of jobs; a change to any field of the resolved
scenario (the base file, a default, the seed) makes a new point.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from experiments.spec import SweepSpec, base_path, overrides
from scenario.schema import Scenario, dump_scenario, load_scenario


@dataclass(frozen=True)
class Point:
    """One run of a sweep."""

    values: dict[str, Any]  # the grid combination
    seed: int
    scenario: Scenario = field(compare=False, repr=False)

    @property
    def key(self) -> str:
        return point_key(self.scenario)

    @property
    def grid_id(self) -> str:
        """The grid combination, as text (the points of one grid point differ by seed only)."""
        return json.dumps(self.values, sort_keys=True)

    def label(self) -> str:
        return " ".join(f"{k}={v}" for k, v in self.values.items()) + f" seed={self.seed}"


def point_key(scenario: Scenario) -> str:
    """sha256 of the resolved scenario (seed included), as canonical JSON."""
    canonical = json.dumps(scenario.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(canonical.encode()).hexdigest()


def make_point(spec: SweepSpec, base: Path, values: dict[str, Any], seed: int) -> Point:
    sc = load_scenario(base, [*overrides(spec.set), *overrides(spec.fields(values)), f"seed={seed}"])
    return Point(values=values, seed=seed, scenario=sc)


def expand(spec: SweepSpec, scenarios_dir: Path, seeds: list[int] | None = None,
           allow_paths: bool = True) -> list[Point]:
    """Every grid combination x every seed, in grid order with seeds innermost."""
    base = base_path(spec.base, scenarios_dir, allow_paths)
    return [make_point(spec, base, values, seed) for values in spec.combinations()
            for seed in (seeds if seeds is not None else spec.seed_list())]


def write_point_config(point: Point, directory: Path) -> Path:
    """The point's resolved scenario as the YAML file its run loads."""
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{point.key[:16]}.yaml"
    path.write_text(dump_scenario(point.scenario))
    return path
