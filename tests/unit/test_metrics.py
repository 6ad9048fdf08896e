"""Bulk histogram observations (``fabric.metrics``): the same series as one ``observe`` a value;
the Edge's gauges, a series per Edge."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Histogram

from fabric.metrics import observe_all, observe_many

BUCKETS = (0.001, 0.005, 0.1)
VALUES = [(0.0, 1), (0.001, 3), (0.002, 2), (0.1, 1), (5.0, 4), (0.0049, 1)]


def samples(registry: CollectorRegistry, name: str) -> list[tuple[str, dict[str, str], float]]:
    return [(s.name.removeprefix(name), s.labels, round(s.value, 12))
            for m in registry.collect() if m.name == name
            for s in m.samples if not s.name.endswith("_created")]


def test_observe_many_and_observe_all_equal_repeated_observe() -> None:
    registry = CollectorRegistry()
    many = Histogram("many", "", buckets=BUCKETS, registry=registry)
    every = Histogram("every", "", buckets=BUCKETS, registry=registry)
    single = Histogram("single", "", buckets=BUCKETS, registry=registry)
    for value, count in VALUES:
        observe_many(many, value, count)
        for _ in range(count):
            single.observe(value)
    observe_all(every, [v for v, n in VALUES for _ in range(n)])
    observe_all(every, [])
    assert samples(registry, "many") == samples(registry, "single")
    assert samples(registry, "every") == samples(registry, "single")


def test_the_edge_gauges_have_a_series_per_edge_and_none_where_no_edge_runs() -> None:
    from prometheus_client import REGISTRY

    from domain.edge_side import CoDesign
    from scenario.schema import PolicyConfig

    names = ("cosim_edge_pdp_fill", "cosim_edge_pdp_cap", "cosim_edge_loops_served", "cosim_edge_queueing_delay_seconds")
    assert all(REGISTRY.get_sample_value(n) is None for n in names), "no unlabelled series to plot as 0"
    CoDesign(PolicyConfig(name="heuristic"), 0.3, name="edge-g7").period(100_000)
    assert all(REGISTRY.get_sample_value(n, {"edge": "edge-g7"}) is not None for n in names)
