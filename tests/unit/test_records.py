"""Table parts streamed over the bus: the coordinator's copy is the file a writer on the run
directory would have written, readable batch by batch while it comes in, and a part cut off with
its node keeps every whole batch that came."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fabric import keys
from fabric.bus import InMemoryBus, InMemoryHub
from fabric.records import HEADER, PartStream, RecordSink
from fabric.tables import PACKETS, PartInfo, TableWriter, merge_parts, part_path, read_part

RUN = "r1"


def packet(i: int) -> dict[str, Any]:
    return {"packet_id": i, "flow": "camera-0/video", "ue": "camera-0", "dir": "ul", "size_bytes": 1500,
            "enqueue_us": 1000 * i, "deliver_us": 1000 * i + 3000, "latency_us": 3000, "lost_cause": None,
            "gnb": None}


def write(out: Any, n: int, close: bool = True) -> TableWriter:
    now = [0]
    w = TableWriter(out, PACKETS, "packets", lambda: now[0], max_rows=4)
    for i in range(n):
        now[0] = 1000 * i
        w.append(packet(i))
    if close:
        w.close()
    return w


def test_a_streamed_part_is_the_file_a_writer_on_the_run_directory_writes(tmp_path: Path) -> None:
    hub = InMemoryHub()
    sink = RecordSink(InMemoryBus(hub), RUN, tmp_path / "run", ["netsim"])
    write(PartStream(InMemoryBus(hub), keys.record(RUN, "netsim", "packets")), 10)
    assert sink.settle({"netsim": ["packets"]}, timeout_s=10) == {}
    sink.close()
    local = write(tmp_path / "local.arrows", 10)
    assert local.path is not None
    assert part_path(tmp_path / "run", "packets", "netsim").read_bytes() == local.path.read_bytes()
    assert merge_parts(tmp_path / "run", "packets")["parts"]["netsim"] == {"rows": 10, "complete": True,
                                                                          "upto_s": 0.009}


def test_a_part_cut_off_with_its_node_keeps_every_batch_that_came(tmp_path: Path) -> None:
    hub = InMemoryHub()
    sink = RecordSink(InMemoryBus(hub), RUN, tmp_path, ["camera-0"])
    stream = PartStream(InMemoryBus(hub), keys.record(RUN, "camera-0", "packets"))
    write(stream, 10, close=False)  # two batches of 4 sent, 2 rows buffered when the node is lost
    assert sink.settle({"camera-0": ["packets"]}, timeout_s=0.2) == {"packets-camera-0": "incomplete"}
    sink.close()
    info = PartInfo()
    rows = [r["packet_id"] for b in read_part(part_path(tmp_path, "packets", "camera-0"), info)
            for r in b.to_pylist()]
    assert rows == list(range(8)) and not info.complete and info.upto_us == 7000


def test_a_gap_in_a_part_ends_it_there_and_is_reported(tmp_path: Path) -> None:
    hub = InMemoryHub()
    bus = InMemoryBus(hub)
    sink = RecordSink(bus, RUN, tmp_path, ["edge"])
    key = keys.record(RUN, "edge", "jobs")
    bus.publish(key, HEADER.pack(0, False) + b"abc")
    bus.publish(key, HEADER.pack(2, True) + b"def")  # message 1 never came
    # Ended on the gap: not waited for (a long timeout would fail the test's time, not it).
    assert sink.settle({"edge": ["jobs"]}, timeout_s=60) == {"jobs-edge": "message 2 came where 1 was due"}
    assert sink.errors() == {"jobs-edge": "message 2 came where 1 was due"}
    sink.close()
    assert part_path(tmp_path, "jobs", "edge").read_bytes() == b"abc"


def test_a_part_that_is_none_of_the_runs_is_dropped_and_none_is_written_over(tmp_path: Path) -> None:
    hub = InMemoryHub()
    bus = InMemoryBus(hub)
    sink = RecordSink(bus, RUN, tmp_path, ["edge", "physics"])
    bus.publish(keys.record(RUN, "edge", "secrets"), HEADER.pack(0, True) + b"abc")  # no run table
    bus.publish(keys.record(RUN, "..", "jobs"), HEADER.pack(0, True) + b"abc")  # no federate of the run
    written = part_path(tmp_path, "tasks", "physics")
    written.parent.mkdir(parents=True)
    written.write_bytes(b"physics' own")  # a federate that writes into the run directory
    bus.publish(keys.record(RUN, "physics", "tasks"), HEADER.pack(0, True) + b"abc")
    assert sink.settle({"physics": ["tasks"]}, timeout_s=60)["tasks-physics"].startswith("not written")
    sink.close()
    assert sorted(p.name for p in (tmp_path / "tables").iterdir()) == ["tasks-physics.arrows"]
    assert written.read_bytes() == b"physics' own"
