"""Table parts streamed over the bus: a federate whose node does not see the run directory sends
each part's bytes to the coordinator as it writes them (``PartStream``), and the coordinator
appends them to the same part file in the run directory (``RecordSink``). What reached the
coordinator stays there whatever becomes of the node (docs/architecture.md sec. 9, "Tables").
"""

from __future__ import annotations

import logging
import queue
import struct
import threading
import time
from collections.abc import Iterable
from pathlib import Path
from typing import IO

from fabric import keys
from fabric.bus import Bus
from fabric.tables import TABLES, part_path

log = logging.getLogger(__name__)

# Each message: its number in the part (from 0), whether it is the part's last, then bytes.
HEADER = struct.Struct("<IB")


class PartStream:
    """A write-only file whose bytes leave on the bus: ``write`` buffers, ``flush`` sends what is
    buffered as one message, ``close`` sends the rest as the part's last message. The table
    writer flushes after every batch, so the coordinator holds each batch once it is written."""

    def __init__(self, bus: Bus, key: str) -> None:
        self.bus = bus
        self.key = key
        self.closed = False
        self._buf = bytearray()
        self._sent = 0  # messages sent
        self._pos = 0

    def writable(self) -> bool:
        return True

    def write(self, data: bytes | bytearray | memoryview) -> int:
        if self.closed:
            raise ValueError(f"{self.key}: write to a closed part")
        self._buf += data
        self._pos += len(data)
        return len(data)

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        if self._buf and not self.closed:
            self._send(last=False)

    def close(self) -> None:
        if not self.closed:
            self._send(last=True)
            self.closed = True

    def _send(self, last: bool) -> None:
        self.bus.publish(self.key, HEADER.pack(self._sent, last) + bytes(self._buf))
        self._sent += 1
        self._buf.clear()


class _Part:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.next = 0  # the message expected next
        self.complete = False
        self.error: str | None = None
        self.file: IO[bytes] | None = None
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            self.file = open(path, "xb")  # never over a part written there already
        except OSError as exc:
            self.error = f"not written: {exc}"


class RecordSink:
    """The coordinator's side: writes every streamed part of run ``run_id``'s ``federates`` into
    ``run_dir``'s ``tables/`` folder, byte for byte as the federate's writer produced it (a part
    of another name, or of a table that is none of the run's, is dropped). Messages are taken in
    on the bus's thread and written on a thread of the sink's own."""

    def __init__(self, bus: Bus, run_id: str, run_dir: Path, federates: Iterable[str]) -> None:
        self.run_id = run_id
        self.run_dir = run_dir
        self.federates = set(federates)
        self._parts: dict[tuple[str, str], _Part] = {}  # (federate, table) -> its file
        self._queue: queue.SimpleQueue[tuple[str, bytes] | None] = queue.SimpleQueue()
        self._changed = threading.Condition()
        self._thread = threading.Thread(target=self._write, name=f"records-{run_id}", daemon=True)
        self._thread.start()
        self._closed = False
        bus.subscribe(keys.records_all(run_id), self._on_message)

    def _on_message(self, key: str, payload: bytes) -> None:
        self._queue.put((key, payload))

    def _write(self) -> None:
        while (item := self._queue.get()) is not None:
            key, payload = item
            federate, table = key.rsplit("/", 2)[-2:]
            if table not in TABLES or federate not in self.federates:
                log.error("%s: a streamed part on %s is none of the run's tables: dropped", self.run_id, key)
                continue
            with self._changed:
                try:
                    self._take(federate, table, payload)
                except (OSError, struct.error) as exc:
                    part = self._parts.get((federate, table))
                    if part is not None:  # _end logs it
                        self._end(part, f"not written: {exc}")
                    else:  # failed before its part existed: nothing else would say so
                        log.error("%s: the streamed part %s of %s cannot be written: %s", self.run_id,
                                  table, federate, exc)
                self._changed.notify_all()

    def _take(self, federate: str, table: str, payload: bytes) -> None:
        part = self._parts.get((federate, table))
        if part is None:
            part = self._parts[(federate, table)] = _Part(part_path(self.run_dir, table, federate))
            if part.error:
                log.error("%s: streamed part %s %s", self.run_id, part.path.name, part.error)
        if part.file is None:  # ended: complete, cut by a gap, or never opened
            return
        number, last = HEADER.unpack_from(payload)
        if number != part.next:
            # The bus delivers a publisher's messages reliably and in order: a gap means lost bytes.
            self._end(part, f"message {number} came where {part.next} was due")
            return
        part.file.write(payload[HEADER.size:])
        part.file.flush()
        part.next += 1
        if last:
            part.complete = True
            self._end(part, None)

    def _end(self, part: _Part, error: str | None) -> None:
        if error is not None:
            part.error = error
            log.error("%s: streamed part %s %s", self.run_id, part.path.name, error)
        if part.file is not None:
            part.file.close()
            part.file = None

    def settle(self, tables: dict[str, Iterable[str]], timeout_s: float) -> dict[str, str]:
        """Wait up to ``timeout_s`` until every part that ``tables`` names (a streaming federate
        -> the tables it reported closed) has come in whole, or ended on an error; the parts
        that did not come in whole, as ``table-federate`` -> what is wrong."""
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while True:
                parts = {f"{t}-{f}": self._parts.get((f, t)) for f, names in tables.items() for t in names}
                waiting = [n for n, p in parts.items() if p is None or not (p.complete or p.error)]
                left = deadline - time.monotonic()
                if not waiting or left <= 0:
                    return {n: "incomplete" if p is None or p.error is None else p.error
                            for n, p in sorted(parts.items()) if p is None or not p.complete}
                self._changed.wait(left)

    def errors(self) -> dict[str, str]:
        """Parts cut short by a gap or a write error: ``table-federate`` -> what happened."""
        with self._changed:
            return {f"{t}-{f}": p.error for (f, t), p in sorted(self._parts.items()) if p.error}

    def close(self) -> None:
        """Write what has come and close every file; the parts not complete stay as they are
        (their readers stop at the last whole batch). A second call does nothing."""
        if self._closed:
            return
        self._closed = True
        self._queue.put(None)
        self._thread.join()
        with self._changed:
            for part in self._parts.values():
                if part.file is not None:
                    part.file.close()
                    part.file = None
