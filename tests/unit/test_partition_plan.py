"""A run split into netsim partitions by gNB (domain/partitions.py): contiguous blocks of gNBs
balanced by the radios they serve, each radio's packets routed to its gNB's partition, the
federates named so that their order is the gNBs', and the scenario refusing what cannot be
split."""

from __future__ import annotations

from pathlib import Path

import pytest

from coordinator.edges import provide_edge_plan, serving_gnbs
from coordinator.run import federate_specs
from domain.partitions import (
    PARTITION_FILE,
    load_plan,
    load_route,
    make_plan,
    netsim_name,
    netsim_names,
    split_gnbs,
)
from scenario.schema import ScenarioError, parse_scenario

FACTORY = {"loops": 40, "detailed_loops": 0,
           "hall": {"work_cells_per_row": 20, "work_cell_pitch_m": [4.0, 8.0],
                    "inf_layout": {"sub_scenario": "SL", "gnb_count": 4}}}


def test_gnbs_split_in_contiguous_blocks_balanced_by_radios() -> None:
    assert split_gnbs([10, 10, 10, 10], 2) == (0, 0, 1, 1)
    assert split_gnbs([10, 10, 10, 10], 4) == (0, 1, 2, 3)
    assert split_gnbs([30, 2, 2, 2, 2, 2], 2) == (0, 1, 1, 1, 1, 1)
    # A partition keeps at least one gNB even where the radios would leave it none.
    assert split_gnbs([0, 0, 0, 40], 3) == (0, 0, 1, 2)
    assert split_gnbs([5] * 18, 1) == (0,) * 18
    with pytest.raises(ValueError, match="at most one a gNB"):
        split_gnbs([1, 1], 3)


def test_partition_names_sort_as_their_gnbs() -> None:
    names = [netsim_name(p) for p in range(18)]
    assert names == sorted(names) and names[9] == "netsim-09" and names[10] == "netsim-10"


def test_the_plan_routes_each_radio_to_its_gnbs_partition(tmp_path: Path) -> None:
    sc = parse_scenario(FACTORY, ["partitions=2"])
    assert netsim_names(sc) == ["netsim-00", "netsim-01"]
    provide_edge_plan(sc, tmp_path)
    plan = load_plan(sc, tmp_path)
    serving = serving_gnbs(sc)
    assert plan.count == 2 and sorted(plan.own_gnbs(0) + plan.own_gnbs(1)) == [0, 1, 2, 3]
    route = load_route(sc, tmp_path)
    for radio, g in serving.items():
        assert route.netsim_of(radio) == netsim_name(plan.gnb_partition[g])
    assert {route.netsim_of(r) for r in serving} == {"netsim-00", "netsim-01"}
    with pytest.raises(ValueError, match="no radio 'camera-99'"):
        route.netsim_of("camera-99")
    # One partition: every packet goes to netsim, and no plan file is written or read.
    one = parse_scenario(FACTORY)
    assert load_route(one, tmp_path / "none").netsim_of("camera-3") == "netsim"


def test_a_missing_or_foreign_plan_is_named(tmp_path: Path) -> None:
    sc = parse_scenario(FACTORY, ["partitions=2"])
    with pytest.raises(ValueError, match=f"{PARTITION_FILE} is missing"):
        load_plan(sc, tmp_path)
    from domain.partitions import write_plan
    write_plan(make_plan(parse_scenario(FACTORY, ["partitions=3"]), {"camera-0": 0}, 4), tmp_path)
    with pytest.raises(ValueError, match="into 3 partitions, the scenario into 2"):
        load_plan(sc, tmp_path)


def test_partitions_are_processes_of_their_own_beside_the_core_group() -> None:
    specs = {s.name: s for s in federate_specs(parse_scenario(FACTORY, ["partitions=2"]))}
    assert {"netsim-00", "netsim-01"} <= set(specs)
    assert [m for m, _ in specs["core"].members] == ["physics", "loops"]
    whole = {s.name: s for s in federate_specs(parse_scenario(FACTORY))}
    assert [m for m, _ in whole["core"].members] == ["physics", "netsim", "loops"]


@pytest.mark.parametrize(("sets", "message"), [
    (["partitions=5"], r"partitions = 5 is above the 4 gNBs of hall.inf_layout: at most one "
                       r"partition a gNB \(1..4\)"),
    (["partitions=2", "agvs.count=1", "netsim.handover.interruption_ms=0"],
     r"partitions = 2 with agvs.count = 1 needs netsim.handover.interruption_ms of at least 0.001 \(it is 0\)"),
    (["partitions=0"], r"partitions"),
])
def test_a_partition_count_that_does_not_fit_is_refused(sets: list[str], message: str) -> None:
    with pytest.raises(ScenarioError, match=message):
        parse_scenario(FACTORY, sets)


def test_partitions_need_several_gnbs() -> None:
    with pytest.raises(ScenarioError, match=r"partitions = 2 splits netsim by gNB: set hall.inf_layout"):
        parse_scenario({"loops": 4}, ["partitions=2"])
