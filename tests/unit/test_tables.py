"""Streamed record tables: bounded batches, parts readable up to a crash, merged with fixed columns."""

from __future__ import annotations

import dataclasses
import json
import threading
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from prometheus_client import REGISTRY

from fabric import tables
from fabric.bus import InMemoryBus, InMemoryHub
from fabric.compute import ComputeNode, JobRecord
from fabric.driver import WindowDriver
from fabric.federate import JOB_METRICS_EVERY_US, Federate, FederateContext
from fabric.messages import Advance
from fabric.seeding import rng
from fabric.tables import (
    PACKETS,
    PartInfo,
    TableError,
    TableWriter,
    merge_parts,
    part_path,
    read_part,
)
from scenario.schema import NodeProfile, parse_scenario


def packet(i: int, lost: bool = False) -> dict[str, Any]:
    return {"packet_id": i, "flow": "camera-0/video", "ue": "camera-0", "dir": "ul", "size_bytes": 1500,
            "enqueue_us": 1000 * i, "deliver_us": None if lost else 1000 * i + 3000,
            "latency_us": None if lost else 3000, "lost_cause": "channel" if lost else None, "gnb": None}


def read_all(path: Path) -> tuple[list[dict[str, Any]], PartInfo]:
    info = PartInfo()
    rows = [r for b in read_part(path, info) for r in b.to_pylist()]
    return rows, info


def test_rows_are_written_in_bounded_batches_and_the_part_closed(tmp_path: Path) -> None:
    now = [0]
    w = TableWriter(part_path(tmp_path, "packets", "netsim"), PACKETS, "packets", lambda: now[0], max_rows=4)
    for i in range(10):
        now[0] = 1000 * i
        w.append(packet(i, lost=i % 3 == 0))
        assert w.buffered < 4  # what a federate holds in memory stays bounded
    assert w.rows_written == 8
    rows, info = read_all(w.path)  # readable while the writer is open: two full batches
    assert [r["packet_id"] for r in rows] == list(range(8)) and not info.complete
    w.close()
    rows, info = read_all(w.path)
    assert rows == [packet(i, lost=i % 3 == 0) for i in range(10)]
    assert info.complete and info.rows == 10 and info.upto_us == 9000


def test_a_part_cut_short_keeps_every_whole_batch(tmp_path: Path) -> None:
    w = TableWriter(part_path(tmp_path, "packets", "netsim"), PACKETS, "packets", lambda: 0, max_rows=5)
    w.extend([packet(i) for i in range(12)])  # two batches on disk, two rows buffered
    size = w.path.stat().st_size
    w.flush()
    data = w.path.read_bytes()
    w.path.write_bytes(data[:size + (len(data) - size) // 2])  # the writer died mid-batch
    rows, info = read_all(w.path)
    assert [r["packet_id"] for r in rows] == list(range(10))
    assert not info.complete and info.error and "cut short after 10 rows" in info.error


def test_extend_writes_the_batches_repeated_appends_write(tmp_path: Path) -> None:
    def batches(path: Path) -> list[list[int]]:
        return [[r["packet_id"] for r in b.to_pylist()] for b in read_part(path)]

    one = TableWriter(tmp_path / "one.arrows", PACKETS, "packets", lambda: 0, max_rows=4)
    many = TableWriter(tmp_path / "many.arrows", PACKETS, "packets", lambda: 0, max_rows=4)
    for chunk in ([0, 1], [2, 3, 4, 5, 6, 7, 8, 9, 10], [], [11], [12, 13, 14]):
        for i in chunk:
            one.append(packet(i))
        many.extend([packet(i) for i in chunk])
        assert many.buffered == one.buffered < 4 and many.rows_written == one.rows_written
    one.close()
    many.close()
    assert batches(many.path) == batches(one.path) == [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10, 11],
                                                      [12, 13, 14]]


def test_a_batch_is_the_one_from_pylist_builds(tmp_path: Path) -> None:
    rows = [packet(i, lost=i % 2 == 0) for i in range(7)]
    rows[3] = {k: v for k, v in rows[3].items() if k != "lost_cause"}  # a missing key is null
    w = TableWriter(tmp_path / "p.arrows", PACKETS, "packets", lambda: 0)
    w.extend(rows)
    w.close()
    written = [b for b in read_part(w.path) if b.num_rows]
    assert len(written) == 1
    expected = pa.RecordBatch.from_pylist(rows, schema=PACKETS)
    assert written[0].schema == expected.schema and written[0].equals(expected)


def columns(rows: list[dict[str, Any]]) -> dict[str, list[Any]]:
    return {name: [r.get(name) for r in rows] for name in PACKETS.names}


def test_rows_given_as_columns_write_what_appends_write(tmp_path: Path) -> None:
    def batches(path: Path) -> list[list[dict[str, Any]]]:
        return [b.to_pylist() for b in read_part(path)]

    one = TableWriter(tmp_path / "one.arrows", PACKETS, "packets", lambda: 0, max_rows=4)
    cols = TableWriter(tmp_path / "cols.arrows", PACKETS, "packets", lambda: 0, max_rows=4)
    for chunk in ([0, 1], [2, 3, 4, 5, 6, 7, 8, 9, 10], [], [11], [12, 13, 14]):
        rows = [packet(i, lost=i % 3 == 0) for i in chunk]
        for r in rows:
            one.append(r)
        cols.extend_columns(columns(rows))
        assert cols.buffered == one.buffered < 4 and cols.rows_written == one.rows_written
    one.close()
    cols.close()
    assert batches(cols.path) == batches(one.path)
    assert [len(b) for b in batches(cols.path)] == [4, 4, 4, 3]


def test_rows_as_columns_and_one_by_one_keep_their_order(tmp_path: Path) -> None:
    w = TableWriter(tmp_path / "mixed.arrows", PACKETS, "packets", lambda: 0, max_rows=100)
    w.append(packet(0))
    w.extend_columns({k: v for k, v in columns([packet(1), packet(2)]).items() if k != "lost_cause"})
    w.extend([packet(3)])
    w.extend_columns(columns([packet(4)]))
    w.close()
    rows, info = read_all(w.path)
    assert [r["packet_id"] for r in rows] == [0, 1, 2, 3, 4] and info.complete
    assert rows[1] == packet(1)  # a column not given is null


def test_columns_that_do_not_fit_name_the_table_and_column(tmp_path: Path) -> None:
    w = TableWriter(tmp_path / "bad.arrows", PACKETS, "packets", lambda: 0)
    with pytest.raises(TableError, match="table packets: no column jitter_us"):
        w.extend_columns({**columns([packet(0)]), "jitter_us": [4]})
    with pytest.raises(TableError, match="table packets: columns of different lengths"):
        w.extend_columns({"packet_id": [1, 2], "flow": ["f"]})
    w.extend_columns({**columns([packet(1)]), "size_bytes": ["large"]})
    with pytest.raises(TableError, match="table packets: a row does not fit the columns: column "
                       "size_bytes"):
        w.flush()


def test_a_row_with_an_unknown_column_names_the_table_and_column(tmp_path: Path) -> None:
    w = TableWriter(part_path(tmp_path, "packets", "netsim"), PACKETS, "packets", lambda: 0)
    w.append({**packet(0), "jitter_us": 4})
    with pytest.raises(TableError, match="table packets: no column jitter_us"):
        w.flush()
    w = TableWriter(part_path(tmp_path, "packets", "edge"), PACKETS, "packets", lambda: 0)
    w.append({**packet(1), "size_bytes": "large"})
    with pytest.raises(TableError, match="table packets: a row does not fit the columns: column "
                       "size_bytes"):
        w.flush()


def test_merge_gives_the_table_columns_for_parts_and_for_none(tmp_path: Path) -> None:
    for fed, ids in (("camera-0", range(3)), ("edge", range(3, 5))):
        w = TableWriter(part_path(tmp_path, "packets", fed), PACKETS, "packets", lambda: 7000)
        w.extend([packet(i) for i in ids])
        if fed == "camera-0":
            w.close()
        else:
            w.flush()  # a federate that died after its last flush
    summary = merge_parts(tmp_path, "packets")
    assert summary["rows"] == 5
    assert summary["parts"]["camera-0"] == {"rows": 3, "complete": True, "upto_s": 0.007}
    assert summary["parts"]["edge"]["complete"] is False
    merged = pq.read_table(tmp_path / "packets.parquet")
    assert merged.schema.names == PACKETS.names
    assert sorted(merged.column("packet_id").to_pylist()) == list(range(5))
    assert not list((tmp_path / "tables").glob("*.arrows"))
    assert merge_parts(tmp_path, "packets")["rows"] == 5  # merging again keeps what was merged
    empty = merge_parts(tmp_path, "tasks")
    assert empty == {"rows": 0, "parts": {}}
    assert pq.read_table(tmp_path / "tasks.parquet").schema.names == tables.TASKS.names


def test_the_jobs_table_has_every_field_of_a_job_record() -> None:
    assert {f.name for f in dataclasses.fields(JobRecord)} == set(tables.JOBS.names)


class Counter(Federate):
    """Records one packet row per millisecond of simulated time."""

    def setup(self) -> None:
        self.rows = self.table("packets")
        self.schedule(0, self.tick)

    def tick(self) -> None:
        self.rows.append(packet(self.now // 1000))
        self.schedule(self.now + 1000, self.tick)


def test_a_federate_flushes_every_few_simulated_seconds(tmp_path: Path) -> None:
    from coordinator.conductor import Conductor

    assert tables.FLUSH_EVERY_US // 1000 < tables.MAX_BATCH_ROWS  # flushed by time, not by rows
    hub = InMemoryHub()
    sc = parse_scenario({"duration_s": 10})
    fed = Counter(FederateContext("netsim", "t1", sc, tmp_path), InMemoryBus(hub))
    end_us = tables.FLUSH_EVERY_US + 500_000
    conductor = Conductor(InMemoryBus(hub), "t1", ["netsim"], 1000, end_us, window_timeout_s=10)
    thread = threading.Thread(target=WindowDriver(fed).serve, daemon=True)
    thread.start()
    conductor.wait_ready(10)
    conductor.run()
    # Still running: the rows of the first FLUSH_EVERY_US are on disk, the rest buffered.
    rows, info = read_all(part_path(tmp_path, "packets", "netsim"))
    assert len(rows) == tables.FLUSH_EVERY_US // 1000 and info.upto_us == tables.FLUSH_EVERY_US
    assert fed.rows.buffered == end_us // 1000 - len(rows)
    stopped = conductor.stop("completed", timeout_s=10)
    thread.join(10)
    rows, info = read_all(part_path(tmp_path, "packets", "netsim"))
    assert len(rows) == end_us // 1000 and info.complete
    assert stopped["netsim"].summary["records"] == {"packets": end_us // 1000}
    assert stopped["netsim"].summary["peak_rss_mb"] > 0


def test_a_flush_with_no_new_rows_still_says_how_far_the_part_is_complete(tmp_path: Path) -> None:
    now = [0]
    w = TableWriter(part_path(tmp_path, "packets", "netsim"), PACKETS, "packets", lambda: now[0])
    w.append(packet(0))
    w.flush()
    now[0] = 7000
    w.flush()  # nothing new since: the reach moves on all the same
    rows, info = read_all(w.path)
    assert len(rows) == 1 and info.upto_us == 7000 and not info.complete


class Quiet(Federate):
    """Records one row at 0 and has nothing to do after it: it sits the later windows out."""

    def setup(self) -> None:
        self.rows = self.table("packets")
        self.schedule(0, lambda: self.rows.append(packet(0)))


def test_a_federate_that_sat_the_last_windows_out_is_complete_up_to_the_runs_stop(tmp_path: Path) -> None:
    from coordinator.conductor import Conductor

    hub = InMemoryHub()
    sc = parse_scenario({"duration_s": 1})
    fed = Quiet(FederateContext("edge", "t1", sc, tmp_path), InMemoryBus(hub))
    conductor = Conductor(InMemoryBus(hub), "t1", ["edge"], 1000, 50_000, window_timeout_s=10)
    thread = threading.Thread(target=WindowDriver(fed).serve, daemon=True)
    thread.start()
    conductor.wait_ready(10)
    conductor.run()
    conductor.stop("completed", timeout_s=10)
    thread.join(10)
    rows, info = read_all(part_path(tmp_path, "packets", "edge"))
    assert len(rows) == 1 and info.complete and info.upto_us == 50_000


def test_a_salvaged_run_reaches_as_far_as_its_parts_left_open(tmp_path: Path) -> None:
    from coordinator.run import close_records

    for federate, upto_us, closed in (("edge", 1000, True), ("netsim", 26_000, False), ("loops", 27_000, False)):
        w = TableWriter(part_path(tmp_path, "packets", federate), PACKETS, "packets", lambda u=upto_us: u)
        w.append(packet(upto_us))
        w.close() if closed else w.flush()
    assert close_records(tmp_path)["sim_time_reached_s"] == pytest.approx(0.026)


def test_a_run_whose_coordinator_died_is_closed_when_a_coordinator_starts(tmp_path: Path) -> None:
    """The API's store still says "running" and the run has only its streamed parts: the next
    coordinator marks it failed and merges the parts, kpis.json saying how far it got."""
    from experiments.job_store import JobKind, JobStore
    from experiments.jobs import ORPHAN_REASON, JobService


    run_dir = tmp_path / "runs" / "r1"
    now = [0]
    w = TableWriter(part_path(run_dir, "packets", "netsim"), PACKETS, "packets", lambda: now[0], max_rows=4)
    for i in range(6):
        now[0] = 1000 * i
        w.append(packet(i))
    w.flush()  # the federate streamed 6 rows, then everything died: the part was never closed
    store = JobStore(tmp_path / "runs.sqlite")
    store.add("r1", JobKind.RUN, "smoke", {}, run_dir)
    store.set_running("r1")
    store.close()
    jobs = JobService(tmp_path / "runs.sqlite", tmp_path / "runs", tmp_path / "sweeps", tmp_path)
    assert jobs.store.get("r1")["state"] == "failed"
    jobs.close()
    kpis = json.loads((run_dir / "kpis.json").read_text())
    assert kpis["status"] == "failed" and kpis["reason"] == ORPHAN_REASON
    assert kpis["recorded"]["rows"]["packets"] == 6
    assert kpis["recorded"]["sim_time_reached_s"] == pytest.approx(0.005)
    assert pq.read_table(run_dir / "packets.parquet").num_rows == 6


class Worker(Federate):
    """Holds many compute nodes and runs one job on the first every millisecond."""

    def setup(self) -> None:
        self.nodes = [ComputeNode(f"worker-{k}", NodeProfile(cpus=1.0, timing="model"), rng(1, f"worker-{k}"))
                      for k in range(50)]
        self.record_jobs(*self.nodes)
        self.schedule(0, self.tick)

    def tick(self) -> None:
        self.nodes[0].run("compress", self.now, int)
        self.schedule(self.now + 1000, self.tick)


def test_job_metrics_move_in_every_100_simulated_ms_from_the_nodes_that_ran(tmp_path: Path) -> None:
    """1-ms windows do not publish every window: the jobs wait for the next 100 ms, and nodes
    with no job are not visited."""
    fed = Worker(FederateContext("loops", "t1", parse_scenario({"duration_s": 1}), tmp_path),
                 InMemoryBus(InMemoryHub()))
    fed.setup()

    def published() -> float:
        return REGISTRY.get_sample_value("cosim_compute_job_duration_seconds_count",
                                         {"node": "worker-0", "kind": "compress"}) or 0.0

    for window, end in enumerate(range(1000, JOB_METRICS_EVERY_US + 2000, 1000)):
        adv = Advance(window=window, t_start_us=end - 1000, t_end_us=end, expected_in={})
        fed.begin_window(adv)
        while (key := fed.next_event_key()) is not None and key[0] < end:
            fed.process_next()
        fed.end_window(adv)
        if end == 1000:
            assert published() == 1
        elif end < 1000 + JOB_METRICS_EVERY_US:
            assert published() == 1, f"published at {end} us"
    assert published() == 1 + JOB_METRICS_EVERY_US // 1000
    assert REGISTRY.get_sample_value("cosim_compute_job_duration_seconds_count",
                                     {"node": "worker-1", "kind": "compress"}) is None
