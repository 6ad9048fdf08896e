"""The sweep spec: a base scenario, a grid over dotted scenario fields, seeds, and when to stop.

The YAML form: README.md, "Sweeps"; ``variants`` are swept as the grid field ``variant`` (all of
them when the grid leaves it out). Every grid value and combination is validated against the
scenario schema when the spec loads, so a sweep never starts with a point that cannot run.
"""

from __future__ import annotations

import itertools
import json
import math
import re
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, get_args

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from domain.policy import policy_errors
from experiments.summary import references, series_name
from scenario.schema import (
    NAME_MAX,
    SEED_LIMIT,
    Scenario,
    ScenarioError,
    current_path,
    load_scenario,
    shipped_names,
)

SCENARIOS_DIR = Path("configs") / "scenarios"
VARIANT = "variant"  # the grid field that sweeps the spec's named variants
VARIANT_NAME = r"[a-z0-9][a-z0-9_-]*"


class SpecModel(BaseModel):
    model_config = ConfigDict(extra="forbid")


# A spec is counted before anything is expanded: an axis holds at most MAX_AXIS_VALUES values and
# a spec at most MAX_SPEC_POINTS points (grid combinations x seeds); a coordinator may allow fewer.
MAX_AXIS_VALUES = 1000
MAX_SPEC_POINTS = 100_000
# Series (and combinations of the fields ``exclude`` names) walked one by one to count or check
# them; beyond it a spec's count is the grid's, an upper bound, and its reference is not checked.
MAX_SERIES = 4096


class Range(SpecModel):
    """An inclusive arithmetic range of grid values."""

    start: float = Field(allow_inf_nan=False, description="first value")
    stop: float = Field(allow_inf_nan=False, description="last value (included when the steps land on it)")
    step: float = Field(gt=0, allow_inf_nan=False, description="increment, > 0")

    @model_validator(mode="after")
    def _bounded(self) -> Range:
        n = self.count()
        if n > MAX_AXIS_VALUES:
            raise ValueError(f"{self.start:g}..{self.stop:g} step {self.step:g} gives {n:.3g} values; "
                             f"an axis holds at most {MAX_AXIS_VALUES}")
        return self

    def count(self) -> float:
        """How many values the range holds (a float: it may be astronomically many, or inf)."""
        steps = (self.stop - self.start) / self.step
        if not math.isfinite(steps):
            return math.inf
        return max(0.0, math.floor(steps + 1e-9) + 1.0)

    def values(self) -> list[int | float]:
        n = int(self.count())
        out = [self.start + i * self.step for i in range(max(n, 0))]
        if all(float(v).is_integer() for v in (self.start, self.step)):
            return [int(v) for v in out]
        return [round(v, 12) for v in out]


class RepeatUntil(SpecModel):
    """Add seeds to a grid point until its runs hold enough tasks for a meaningful success rate."""

    min_tasks: int = Field(ge=1, description="tasks (over all seeds of a grid point) to reach")
    max_seeds: int = Field(default=10, ge=1, le=100, description="never more seeds than this per grid point")


class CapacitySpec(SpecModel):
    """How capacity is read off the sweep: the load axis and the success thresholds."""

    x: str = Field(default="loops", description="grid field that is the load (the capacity axis)")
    thresholds: list[float] = Field(default_factory=lambda: [1.0, 0.98], min_length=1,
                                    description="task success rates a load must reach, in (0, 1]")
    reference: str | None = Field(
        default=None, description="series the gains are relative to, e.g. `policy.name=none` "
        "(default: the first series of the grid)")
    group: str | None = Field(
        default=None, description="grid field whose values are separate conditions, e.g. `variant` "
        "naming work cells: capacity, the gains over the reference and the invariant (where the "
        "reference places every task, so does each series) are read within each value (default: "
        "one condition)")
    stop_after: int | None = Field(
        default=None, ge=1, description="run loads in ascending order and stop a series once this "
        "many consecutive loads miss the lowest threshold: its larger loads cannot change its "
        "capacity and are not run (default: run every point)")

    @field_validator("thresholds")
    @classmethod
    def _in_unit_interval(cls, v: list[float]) -> list[float]:
        for t in v:
            if not 0 < t <= 1:
                raise ValueError(f"threshold {t} is not in (0, 1]")
        return v


class FigureSpec(SpecModel):
    latency_loads: list[int | float] | None = Field(
        default=None, description="loads (capacity.x values) whose latency CDF is drawn in Fig. 6 "
        "(default: the smallest, a middle and the largest)")
    map_y: str | None = Field(
        default=None, description="a grid field: Fig. 8 maps the task success rate over capacity.x "
        "and this field, one panel per capacity.group value (default: no map)")


class SweepSpec(SpecModel):
    """A whole sweep: every point is base + set + one grid combination, run once per seed."""

    name: str = Field(pattern=r"^[a-z0-9][a-z0-9_-]*$", max_length=NAME_MAX,
                      description=f"sweep name (lower case, digits, _ and -; at most {NAME_MAX} characters)")
    base: str = Field(description="base scenario: a name in configs/scenarios or a path to a YAML file")
    set: dict[str, Any] = Field(default_factory=dict, description="dotted field -> value, fixed for every point")
    grid: dict[str, list[Any] | Range] = Field(min_length=1, max_length=16,
                                                description="dotted field -> values to sweep")
    variants: dict[str, dict[str, Any]] = Field(
        default_factory=dict, description="name -> {dotted field: value}: series that differ in "
        "several fields, swept as the grid field `variant`")
    exclude: list[dict[str, Any]] = Field(
        default_factory=list, max_length=32, description="grid combinations not to run: each entry maps grid "
        "fields to one of their values, and every combination matching all of an entry's fields is "
        "left out, e.g. `{policy.name: none, policy.floor: false}` where a series ignores a field")
    scale: dict[str, str] = Field(
        default_factory=dict, description="grid field -> scenario field whose value multiplies it "
        "in every point, e.g. `loops: hall.inf_layout.gnb_count` sweeps loops per gNB (the grid, "
        "the capacity and the figures keep the per-gNB value; the run gets the product)")
    seeds: int | list[int] = Field(default=1, description="a count n (seeds 1..n) or a list of seeds")
    repeat_until: RepeatUntil | None = Field(default=None, description="add seeds until enough tasks")
    capacity: CapacitySpec = Field(default_factory=CapacitySpec, description="capacity rule")
    figures: FigureSpec = Field(default_factory=FigureSpec, description="figure options")

    @field_validator("seeds")
    @classmethod
    def _seeds(cls, v: int | list[int]) -> int | list[int]:
        if isinstance(v, int):
            if not 1 <= v <= 1000:
                raise ValueError(f"a seed count must be 1..1000, got {v}")
        else:
            if not v:
                raise ValueError("the seed list is empty")
            if len(set(v)) != len(v) or any(not 0 <= s < SEED_LIMIT for s in v):
                raise ValueError(f"seeds must be distinct integers in 0..{SEED_LIMIT - 1}")
        return v

    @field_validator("variants")
    @classmethod
    def _variant_names(cls, v: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
        for name, fields in v.items():
            if not re.fullmatch(VARIANT_NAME, name):
                raise ValueError(f"variant name {name!r}: use lower case, digits, _ and -")
            if not fields:
                raise ValueError(f"variant {name!r} sets no field")
        return v

    @model_validator(mode="after")
    def _variant_axis(self) -> SweepSpec:
        if self.variants and VARIANT not in self.grid:
            self.grid = {VARIANT: list(self.variants), **self.grid}  # every variant, swept first
        if VARIANT in self.grid:
            if not self.variants:
                raise ValueError("grid field `variant` needs a `variants` section naming each one")
            values = self.grid[VARIANT]
            unknown = [v for v in (values.values() if isinstance(values, Range) else values)
                       if not isinstance(v, str) or v not in self.variants]
            if unknown:
                raise ValueError(f"grid.variant: {', '.join(map(repr, unknown))} not in variants "
                                 f"({', '.join(self.variants)})")
        return self

    @model_validator(mode="after")
    def _seeds_only_in_seeds(self) -> SweepSpec:
        # Every point's seed is set last, from `seeds`: one set elsewhere would be replaced
        # without a word, and two grid values of it would be one run.
        where = ["set"] if "seed" in self.set else []
        where += ["grid"] if "seed" in self.grid else []
        where += [f"variants.{name}" for name, fields in self.variants.items() if "seed" in fields]
        if where:
            raise ValueError(f"seed in {', '.join(where)}: a sweep's seeds are its `seeds` (a count "
                             f"n for 1..n, or a list), set on every point")
        return self

    @model_validator(mode="after")
    def _exclusions(self) -> SweepSpec:
        for i, entry in enumerate(self.exclude):
            if not entry:
                raise ValueError(f"exclude[{i}] names no field: give grid fields and a value of each")
            for field, value in entry.items():
                if field not in self.grid:
                    raise ValueError(f"exclude[{i}].{field}: not a grid field; grid fields: "
                                     f"{', '.join(self.grid)}")
                values = self.grid[field]
                allowed = values.values() if isinstance(values, Range) else values
                if value not in allowed:
                    raise ValueError(f"exclude[{i}].{field} = {value!r} is not one of its grid values "
                                     f"({', '.join(map(repr, allowed))})")
        return self

    @model_validator(mode="after")
    def _bounded(self) -> SweepSpec:
        for path, values in self.grid.items():
            if isinstance(values, list) and len(values) > MAX_AXIS_VALUES:
                raise ValueError(f"grid.{path}: {len(values)} values; an axis holds at most {MAX_AXIS_VALUES}")
        if self.points() > MAX_SPEC_POINTS:
            raise ValueError(f"{self.points()} points (grid combinations x seeds); a spec holds at most "
                             f"{MAX_SPEC_POINTS}")
        # Validation walks every combination, the excluded ones too: the grid itself is bounded.
        combos = math.prod(v.count() if isinstance(v, Range) else len(v) for v in self.grid.values())
        if combos > MAX_SPEC_POINTS:
            raise ValueError(f"{combos:.0f} grid combinations (before `exclude`); a spec holds at most "
                             f"{MAX_SPEC_POINTS}")
        if combos and self.points() == 0:
            raise ValueError("exclude: every grid combination is excluded, nothing would run")
        return self

    def points(self) -> int:
        """Grid combinations not ``exclude``d x seeds (the most seeds ``repeat_until`` may add),
        counted without expanding the grid."""
        seeds = len(self.seed_list()) if isinstance(self.seeds, list) else self.seeds
        if self.repeat_until is not None:
            seeds = max(seeds, self.repeat_until.max_seeds)
        named = {f for entry in self.exclude for f in entry}
        combos = named_combos = 1
        for field, values in self.grid.items():
            n = int(values.count()) if isinstance(values, Range) else len(values)
            if field in named:
                named_combos *= n
            else:
                combos *= n
        if named and named_combos <= MAX_SERIES:
            # counted over the fields the entries name, not over the whole grid
            grid = {f: v for f, v in self.grid_values().items() if f in named}
            named_combos = sum(not self.excluded(dict(zip(grid, c, strict=True)))
                               for c in itertools.product(*grid.values()))
        return combos * named_combos * seeds

    @model_validator(mode="after")
    def _capacity_axis(self) -> SweepSpec:
        for name, field in (("x", self.capacity.x), ("group", self.capacity.group)):
            if field is not None and field not in self.grid:
                raise ValueError(f"capacity.{name} = {field!r} is not a grid field; grid fields: "
                                 f"{', '.join(self.grid)}")
        if self.figures.map_y is not None and self.figures.map_y not in self.grid:
            raise ValueError(f"figures.map_y = {self.figures.map_y!r} is not a grid field; grid fields: "
                             f"{', '.join(self.grid)}")
        for field, by in self.scale.items():
            if field not in self.grid or field == VARIANT:
                raise ValueError(f"scale.{field}: not a grid field; grid fields: {', '.join(self.grid)}")
            if by == field:
                raise ValueError(f"scale.{field} = {by!r}: a field cannot scale itself")
        if self.capacity.group == self.capacity.x:
            raise ValueError(f"capacity.group = {self.capacity.group!r} is the load axis capacity.x; "
                             "group by another grid field")
        if self.capacity.reference is not None and (names := self.series_names()) is not None:
            # The reference names a series, or part of one (read within each layout or group):
            # the read-out's own matching (summary.references) must find it for some series.
            if not any(references(names, self.capacity.reference).values()):
                shown = ", ".join(repr(n) for n in names[:12]) + (", ..." if len(names) > 12 else "")
                raise ValueError(f"capacity.reference = {self.capacity.reference!r} names no series of "
                                 f"the grid; its series: {shown}")
        return self

    def seed_list(self) -> list[int]:
        return list(range(1, self.seeds + 1)) if isinstance(self.seeds, int) else list(self.seeds)

    def grid_values(self) -> dict[str, list[Any]]:
        return {k: (v.values() if isinstance(v, Range) else list(v)) for k, v in self.grid.items()}

    def fields(self, values: dict[str, Any]) -> dict[str, Any]:
        """The scenario fields a grid combination sets: a variant stands for its own fields; a
        ``scale``d field is multiplied by its factor's value."""
        out: dict[str, Any] = {}
        for k, v in values.items():
            out.update(self.variants[v] if k == VARIANT else {k: v})
        for field, by in self.scale.items():
            factor = out.get(by, self.set.get(by))
            if field in out and factor is not None:  # a lone axis value (validation) stays as given
                out[field] = out[field] * factor
        return out

    def combinations(self) -> list[dict[str, Any]]:
        """Every grid combination not ``exclude``d, in grid order (the last field varies fastest)."""
        grid = self.grid_values()
        combos = (dict(zip(grid, combo, strict=True)) for combo in itertools.product(*grid.values()))
        return [c for c in combos if not self.excluded(c)]

    def excluded(self, values: dict[str, Any], entries: list[dict[str, Any]] | None = None) -> bool:
        """Whether the grid combination ``values`` matches an ``exclude`` entry (of ``entries``,
        by default all of them)."""
        return any(all(values.get(f) == v for f, v in entry.items())
                   for entry in (self.exclude if entries is None else entries))

    def series_names(self) -> list[str] | None:
        """The names of the series the capacity rule reads (``summary.series_name``), in grid
        order: the combinations of the grid fields other than the load axis and the group, less
        those an ``exclude`` entry of only such fields matches; None where there are more than
        ``MAX_SERIES``."""
        inner = {f: v for f, v in self.grid_values().items()
                 if f not in (self.capacity.x, self.capacity.group)}
        if math.prod(len(v) for v in inner.values()) > MAX_SERIES:
            return None
        whole = [e for e in self.exclude if set(e) <= set(inner)]
        combos = (dict(zip(inner, c, strict=True)) for c in itertools.product(*inner.values()))
        return [series_name(c, list(inner)) for c in combos if not self.excluded(c, whole)]


class SweepError(ValueError):
    """A spec that cannot run; ``errors`` lists (field, message) pairs, like ScenarioError."""

    def __init__(self, errors: list[tuple[str, str]]) -> None:
        self.errors = errors
        super().__init__("; ".join(f"{f}: {m}" for f, m in errors))

    def format(self) -> str:
        return "\n".join(f"  {field}: {msg}" for field, msg in self.errors)


def overrides(values: dict[str, Any]) -> list[str]:
    """``field.path=value`` assignments (values as JSON, which YAML reads back unchanged; what
    JSON has no form for, such as a YAML date, as its text)."""
    return [f"{k}={json.dumps(v, default=str)}" for k, v in values.items()]


def _number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def field_exists(path: str) -> str | None:
    """None if ``path`` names a scenario field, else what is wrong with it."""
    model: Any = Scenario
    parts = path.split(".")
    for i, part in enumerate(parts):
        fields = getattr(model, "model_fields", None)
        if fields is None or part not in fields:
            where = ".".join(parts[:i]) or "the scenario"
            allowed = ", ".join(sorted(fields)) if fields else "(none: not a section)"
            return f"no field {part!r} in {where}; allowed there: {allowed}"
        # A section that may be absent (``X | None``) is a section all the same.
        kinds = [a for a in (fields[part].annotation, *get_args(fields[part].annotation))
                 if isinstance(a, type) and issubclass(a, BaseModel)]
        model = kinds[0] if kinds else None
    return None


def base_path(base: str, scenarios_dir: Path = SCENARIOS_DIR, allow_paths: bool = True) -> Path:
    """The base scenario's file: a shipped name, or (from the CLI only) a path."""
    known = shipped_names(scenarios_dir)
    if base in known:  # a name from the list, never a path built from the request
        return scenarios_dir / f"{base}.yaml"
    if allow_paths and Path(base).is_file():
        return Path(base)
    raise SweepError([("base", f"{base!r} is not a shipped scenario ({', '.join(known)})"
                               + (" nor a file" if allow_paths else ""))])


# Errors of a grid axis's union (a list, or a Range) that only say the value is not the other kind.
UNION_BRANCH_ERRORS = ("list_type", "model_type", "dict_type", "model_attributes_type")


def _format(exc: ValidationError) -> list[tuple[str, str]]:
    out = []
    errors = exc.errors()
    # A grid axis is a list or a range: where the other branch says more of the same field than
    # "not my kind", keep only that.
    said = {e["loc"][:2] for e in errors if e["type"] not in UNION_BRANCH_ERRORS}
    errors = [e for e in errors if e["type"] not in UNION_BRANCH_ERRORS or e["loc"][:2] not in said]
    for err in errors:
        loc = ".".join(str(p) for p in err["loc"]
                       if not str(p).startswith(("list[", "Range", "function-after["))) or "(sweep)"
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "extra_forbidden":
            section: Any = SweepSpec
            for part in err["loc"][:-1]:
                ann = getattr(section, "model_fields", {}).get(part)
                section = getattr(ann, "annotation", None)
            fields = getattr(section, "model_fields", None)
            msg = f"unknown field; allowed here: {', '.join(sorted(fields))}" if fields else "unknown field"
        out.append((loc, msg))
    return out


def _current_paths(data: dict[str, Any]) -> dict[str, Any]:
    """``data`` with every scenario field path under its current name (``scenario.schema.RENAMED``:
    old names load with a warning)."""
    data = dict(data)
    for section in ("set", "grid"):
        if isinstance(data.get(section), dict):
            data[section] = {current_path(k) if isinstance(k, str) else k: v for k, v in data[section].items()}
    if isinstance(data.get("variants"), dict):
        data["variants"] = {name: ({current_path(k) if isinstance(k, str) else k: v for k, v in fields.items()}
                                   if isinstance(fields, dict) else fields)
                            for name, fields in data["variants"].items()}
    if isinstance(data.get("exclude"), list):
        data["exclude"] = [{current_path(k) if isinstance(k, str) else k: v for k, v in entry.items()}
                           if isinstance(entry, dict) else entry for entry in data["exclude"]]
    for section, key in (("capacity", "x"), ("capacity", "group"), ("figures", "map_y")):
        part = data.get(section)
        if isinstance(part, dict) and isinstance(part.get(key), str):
            data[section] = {**part, key: current_path(part[key])}
    return data


def parse_spec(data: Any, scenarios_dir: Path = SCENARIOS_DIR, allow_paths: bool = True,
               max_points: tuple[int, str] | None = None,
               check: Callable[[Scenario], list[tuple[str, str]]] | None = None) -> SweepSpec:
    """Validate a spec mapping, its grid paths, and every point's scenario; or raise SweepError.
    ``max_points`` (this caller's limit on grid combinations x seeds, and the setting's name) is
    checked before any point is: a spec too large to run costs nothing to refuse. ``check``
    (the caller's limits on a scenario: (field, message) pairs) applies to every resolved point,
    whatever sets the field: `set`, a grid value, a variant, a section or a scale."""
    if not isinstance(data, dict):
        raise SweepError([("(sweep)", f"expected a mapping of fields, got {type(data).__name__}")])
    try:
        spec = SweepSpec.model_validate(_current_paths(data))
    except ValidationError as exc:
        raise SweepError(_format(exc)) from None
    if max_points is not None and spec.points() > max_points[0]:
        raise SweepError([("grid", f"{spec.points()} points (grid combinations x seeds), more than this "
                                   f"coordinator runs in one sweep: {max_points[1]} = {max_points[0]}")])
    errors: list[tuple[str, str]] = []
    sections = [("set", list(spec.set)), ("grid", [p for p in spec.grid if p != VARIANT]),
                ("scale", list(spec.scale.values()))]
    sections += [(f"variants.{name}", list(fields)) for name, fields in spec.variants.items()]
    for section, paths in sections:
        for path in paths:
            problem = field_exists(path)
            if problem:
                errors.append((f"{section}.{path}", problem))
            elif section.startswith("variants.") and (path in spec.set or path in spec.grid):
                errors.append((f"{section}.{path}", "also in `set` or `grid`: a variant's field is "
                                                    "neither fixed nor swept"))
    grid = spec.grid_values()
    for field, by in spec.scale.items():
        swept = by in spec.grid or (VARIANT in spec.grid and all(by in f for f in spec.variants.values()))
        if by not in spec.set and not swept:
            errors.append((f"scale.{field}", f"{by!r} is neither in `set`, the grid, nor set by every "
                                             "variant: give the factor of every point"))
            continue
        # Both sides of the product are numbers, checked before any is multiplied.
        factors = ([spec.set[by]] if by in spec.set else grid[by] if by in grid
                   else [f[by] for f in spec.variants.values()])
        for where, values in ((f"grid.{field}", grid[field]), (f"scale.{field}", factors)):
            bad = next((v for v in values if not _number(v)), None)
            if bad is not None:
                errors.append((where, f"{bad!r} is not a finite number: a scaled field and its "
                                      "factor multiply"))
    for path, values in grid.items():
        if not values:
            errors.append((f"grid.{path}", "no values: give at least one"))
        if path in spec.set:
            errors.append((f"grid.{path}", "also in `set`: a field is either fixed or swept"))
    if errors:
        raise SweepError(errors)
    base = base_path(spec.base, scenarios_dir, allow_paths)
    fixed = overrides(spec.set)
    verify = _Verifier(spec, base, fixed, check)
    for path, values in grid.items():  # each value alone, to name the bad one
        seen: dict[str, int] = {}
        for i, v in enumerate(values):
            # A value that scales another axis (a layout's gNB count) comes with that axis's
            # first value: what the base scenario has there is no point of the sweep.
            alone = {**{f: grid[f][0] for f in spec.scale if f != path}, path: v}
            resolved = verify(f"grid.{path}[{i}]", f"{v!r}: ", alone)
            if resolved is None:
                continue
            if (j := seen.setdefault(resolved, i)) != i:  # one run directory per point
                verify.errors.append((f"grid.{path}[{i}]", f"{v!r} gives the points grid.{path}[{j}] "
                                                           f"({values[j]!r}) gives: give each value once"))
    if not verify.errors:
        for combo in spec.combinations():
            verify(f"grid point {combo}", "", combo)
    if verify.errors:
        raise SweepError(verify.errors)
    return spec


# Errors a spec's validation lists before it stops looking: a spec with a bad value in a large
# grid would otherwise load every point to say the same thing.
MAX_ERRORS = 20


class _Verifier:
    """Loads the scenario of a grid combination, gathering its errors and those of the caller's
    ``check`` (its limits); a limit on a field the grid does not sweep is named where that field is
    set (``set.<field>`` or ``base.<field>``), once."""

    def __init__(self, spec: SweepSpec, base: Path, fixed: list[str],
                 check: Callable[[Scenario], list[tuple[str, str]]] | None) -> None:
        self.spec, self.base, self.fixed, self.check = spec, base, fixed, check
        self.errors: list[tuple[str, str]] = []
        swept = [p for p in spec.grid if p != VARIANT]
        if VARIANT in spec.grid:
            swept += [p for fields in spec.variants.values() for p in fields]
        self._swept = swept

    def __call__(self, where: str, prefix: str, values: dict[str, Any]) -> str | None:
        """The resolved scenario of ``values`` as JSON, or None when it has errors."""
        if len(self.errors) >= MAX_ERRORS:
            if self.errors[-1][0] != "(sweep)":
                self.errors.append(("(sweep)", f"more errors not listed: the first {MAX_ERRORS} above"))
            return None
        try:
            sc = load_scenario(self.base, [*self.fixed, *overrides(self.spec.fields(values))])
        except ScenarioError as exc:
            self.errors += [(where, f"{prefix}{f}: {m}") for f, m in exc.errors]
            return None
        found = [self._named(f, m, where, prefix, values.get(VARIANT))
                 for f, m in (self.check(sc) if self.check else [])]
        self.errors += [e for e in found if e not in self.errors]
        return None if found else sc.model_dump_json()

    def _named(self, field: str, message: str, where: str, prefix: str, variant: str | None) -> tuple[str, str]:
        """A limit's error, named where ``field`` gets its value."""
        if variant is not None and self._in(field, self.spec.variants[variant]):
            return f"variants.{variant}.{field}", message
        if self._in(field, self._swept):
            return where, f"{prefix}{field}: {message}"
        return (f"set.{field}" if self._in(field, self.spec.set) else f"base.{field}"), message

    @staticmethod
    def _in(field: str, paths: Iterable[str]) -> bool:
        """Whether one of ``paths`` (dotted) is ``field`` or a section holding it."""
        return any(field == p or field.startswith(p + ".") for p in paths)


def load_spec(path: str | Path, scenarios_dir: Path = SCENARIOS_DIR) -> SweepSpec:
    p = Path(path)
    if not p.is_file():
        raise SweepError([("file", f"{p} does not exist")])
    try:
        data = yaml.safe_load(p.read_text()) or {}
    except (yaml.YAMLError, UnicodeDecodeError, RecursionError) as exc:
        raise SweepError([("file", f"{p} is not valid YAML: {exc}")]) from None
    # Every point's policy as its Edges will build it: a learned model that cannot serve a cell
    # is refused here, not once per point.
    return parse_spec(data, scenarios_dir, check=lambda sc: policy_errors(sc.policy, sc.work_cell))


def dump_spec(spec: SweepSpec) -> str:
    return yaml.safe_dump(spec.model_dump(mode="json", exclude_none=True), sort_keys=False)
