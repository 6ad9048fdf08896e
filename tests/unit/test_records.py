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
    sink = RecordSink(InMemoryBus(hub), RUN, tmp_path / "run")
    write(PartStream(InMemoryBus(hub), keys.record(RUN, "netsim", "packets")), 10)
    assert sink.settle({"netsim": ["packets"]}, timeout_s=10) == []
    sink.close()
    local = write(tmp_path / "local.arrows", 10)
    assert local.path is not None
    assert part_path(tmp_path / "run", "packets", "netsim").read_bytes() == local.path.read_bytes()
    assert merge_parts(tmp_path / "run", "packets")["parts"]["netsim"] == {"rows": 10, "complete": True,
                                                                          "upto_s": 0.009}


def test_a_part_cut_off_with_its_node_keeps_every_batch_that_came(tmp_path: Path) -> None:
    hub = InMemoryHub()
    sink = RecordSink(InMemoryBus(hub), RUN, tmp_path)
    stream = PartStream(InMemoryBus(hub), keys.record(RUN, "camera-0", "packets"))
    write(stream, 10, close=False)  # two batches of 4 sent, 2 rows buffered when the node is lost
    assert sink.settle({"camera-0": ["packets"]}, timeout_s=0.2) == ["packets-camera-0"]
    sink.close()
    info = PartInfo()
    rows = [r["packet_id"] for b in read_part(part_path(tmp_path, "packets", "camera-0"), info)
            for r in b.to_pylist()]
    assert rows == list(range(8)) and not info.complete and info.upto_us == 7000


def test_a_gap_in_a_part_ends_it_there_and_is_reported(tmp_path: Path) -> None:
    hub = InMemoryHub()
    bus = InMemoryBus(hub)
    sink = RecordSink(bus, RUN, tmp_path)
    key = keys.record(RUN, "edge", "jobs")
    bus.publish(key, HEADER.pack(0, False) + b"abc")
    bus.publish(key, HEADER.pack(2, True) + b"def")  # message 1 never came
    assert sink.settle({"edge": ["jobs"]}, timeout_s=0.2) == ["jobs-edge"]
    assert sink.errors() == {"jobs-edge": "message 2 came where 1 was due"}
    sink.close()
    assert part_path(tmp_path, "jobs", "edge").read_bytes() == b"abc"
