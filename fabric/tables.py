"""Result tables: records streamed to disk while a run goes, and Parquet files written atomically.

``TABLES`` fixes every table's columns; a federate streams its rows in bounded batches to an Arrow
IPC part file, merged into ``<run>/<table>.parquet`` when the run ends (``TableWriter``,
``merge_parts``; docs/architecture.md sec. 9, "Tables").
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import pyarrow as pa
import pyarrow.parquet as pq

# A batch is written at the latest after this much simulated time (what a crash can lose) ...
FLUSH_EVERY_US = 2_000_000
# ... or as soon as it holds this many rows (what a federate holds in memory per table).
MAX_BATCH_ROWS = 8192
PART_SUFFIX = ".arrows"

_I = pa.int64()
_F = pa.float64()
_S = pa.string()
_B = pa.bool_()

TASKS = pa.schema([
    ("work_cell", _I), ("task_id", _I), ("spawn_us", _I), ("grasp_us", _I), ("grasp_attempts", _I),
    ("end_us", _I), ("outcome", _S), ("success", _B), ("reason", _S), ("size_m", _F),
    ("mass_kg", _F), ("yaw_rad", _F),
])
"""Per task (physics): one object's life, from spawn to placed, missed, dropped or unfinished."""

PACKETS = pa.schema([
    ("packet_id", _I), ("flow", _S), ("ue", _S), ("dir", _S), ("size_bytes", _I),
    ("enqueue_us", _I), ("deliver_us", _I), ("latency_us", _I), ("lost_cause", _S), ("gnb", _I),
])
"""Per IP packet (netsim): delivery time and latency, or the cause of its loss; the index of the
serving gNB with several (``hall.inf_layout``), else null."""

TRANSMISSIONS = pa.schema([
    ("t_us", _I), ("gnb", _I), ("dir", _S), ("ue", _S), ("n_prb", _I), ("cell_prb", _I),
    ("mcs", _I), ("tx", _I), ("sinr_db", _F), ("ok", _B),
])
"""Per PDSCH/PUSCH transmission of a transport block with several gNBs (netsim): slot start, gNB,
UE, PRBs of the TB and of the cell's carrier, MCS, transmission number, effective SINR, decoded."""

JOBS = pa.schema([
    ("arrival_us", _I), ("cpu_us", _I), ("duration_us", _I), ("end_us", _I), ("kind", _S),
    ("node", _S), ("queue_us", _I), ("start_us", _I), ("throttled_us", _I), ("timing", _S),
    ("wall_us", _I),
])
"""Per compute job (every ComputeNode): ``fabric.compute.JobRecord``."""

FRAMES = pa.schema([
    ("bytes", _I), ("capture_us", _I), ("complete_us", _I), ("detections", _I),
    ("estimator", _S), ("frame_id", _I), ("kept", _B), ("lost", _B), ("loop", _I),
    ("packets", _I), ("pdp", _F), ("ready_us", _I),
])
"""Per frame: camera rows (pdp, kept, bytes, packets) and Edge rows (complete, detections, lost)."""

HANDOVERS = pa.schema([
    ("ue", _S), ("source", _I), ("target", _I), ("start_us", _I), ("end_us", _I),
    ("forwarded", _I), ("lost", _I),
])
"""Per completed handover of a moving radio (netsim): source and target gNB index, the
interruption from start to end, the held packets forwarded to the target or lost."""

TABLES: dict[str, pa.Schema] = {"tasks": TASKS, "packets": PACKETS, "jobs": JOBS, "frames": FRAMES,
                                 "transmissions": TRANSMISSIONS, "handovers": HANDOVERS}


class TableError(ValueError):
    """A row that does not fit its table."""


def part_path(results_dir: Path, table: str, federate: str) -> Path:
    """Where ``federate`` streams its rows of ``table``:
    ``<results_dir>/tables/<table>-<federate>.arrows``."""
    return results_dir / "tables" / f"{table}-{federate}{PART_SUFFIX}"


class PartOut(Protocol):
    """Where a part's bytes go other than a file: written, flushed after each batch, closed."""

    closed: bool

    def write(self, data: bytes) -> int: ...

    def tell(self) -> int: ...

    def flush(self) -> None: ...

    def close(self) -> None: ...


class TableWriter:
    """Appends rows of one table to an Arrow IPC stream file, in batches of bounded size.

    ``out``: the part file, or a writable file object taking its bytes; ``schema``: the table's columns; ``name``: the table's name, for
    errors; ``clock`` gives the simulated time, microseconds, the rows are recorded up to, which
    each batch carries so that a reader can tell how far a federate's records go; ``max_rows``:
    the rows of a batch. ``close`` writes what is buffered and an empty final batch marking the
    part as complete.
    """

    def __init__(self, out: Path | PartOut, schema: pa.Schema, name: str, clock: Callable[[], int],
                 max_rows: int = MAX_BATCH_ROWS) -> None:
        self.path = out if isinstance(out, Path) else None
        self.schema = schema
        self.name = name
        self.clock = clock
        self.max_rows = max_rows
        self.rows_written = 0
        self._rows: list[dict[str, Any]] = []
        # Rows given a column at a time (``extend_columns``): a list per column given, n rows.
        self._cols: dict[str, list[Any]] = {}
        self._ncols = 0
        self._columns = set(schema.names)
        if isinstance(out, Path):
            out.parent.mkdir(parents=True, exist_ok=True)
            self._file: Any = pa.OSFile(str(out), "wb")
        else:  # a file-like object, e.g. a part streamed to the coordinator (``fabric.records``)
            self._file = out
        # Compressed batches: the part of the largest table (packets) is a few bytes a row.
        opts = pa.ipc.IpcWriteOptions(compression="zstd")
        self._writer: Any = pa.ipc.new_stream(self._file, schema, options=opts)
        self.closed = False

    def append(self, row: dict[str, Any]) -> None:
        """Buffer ``row`` (column name -> value; a column left out is null); writes a batch when
        ``max_rows`` are buffered."""
        if self._ncols:
            self.flush()  # rows given as columns go first, in their own batch
        self._rows.append(row)
        if len(self._rows) >= self.max_rows:
            self.flush()

    def extend(self, rows: list[dict[str, Any]]) -> None:
        """``append`` each of ``rows``: the same batches (a write at every ``max_rows``), taken a
        slice at a time rather than a row at a time."""
        if self._ncols and rows:
            self.flush()
        buf = self._rows
        i, n = 0, len(rows)
        while i < n:
            take = min(n - i, self.max_rows - len(buf))
            buf.extend(rows[i : i + take])
            i += take
            if len(buf) >= self.max_rows:
                self.flush()

    def extend_columns(self, columns: dict[str, list[Any]]) -> None:
        """``append`` the rows whose values ``columns`` gives a column at a time (lists of one
        length; a column not given is null), with the same batches, without a dict per row: for
        the tables a federate fills by the thousand a simulated second (netsim's packets)."""
        unknown = columns.keys() - self._columns
        if unknown:
            raise TableError(
                f"table {self.name}: no column {', '.join(sorted(unknown))} (columns: "
                f"{', '.join(self.schema.names)}); add it to fabric/tables.py")
        lengths = {len(v) for v in columns.values()}
        if len(lengths) > 1:
            raise TableError(f"table {self.name}: columns of different lengths {sorted(lengths)}")
        n = lengths.pop() if lengths else 0
        if n and (self._rows or (self._ncols and self._cols.keys() != columns.keys())):
            self.flush()  # rows given one by one, or another set of columns: a batch of their own
        i = 0
        while i < n:
            if not self._ncols:
                self._cols = {name: [] for name in columns}
            take = min(n - i, self.max_rows - self._ncols)
            for name, values in columns.items():
                self._cols[name].extend(values[i:i + take] if take < n else values)
            self._ncols += take
            i += take
            if self._ncols >= self.max_rows:
                self.flush()

    def flush(self, upto_us: int | None = None, closing: bool = False) -> None:
        """Write the buffered rows as one batch (nothing when none are buffered), noting that the
        records are complete up to ``upto_us``, simulated microseconds (default: the clock);
        ``closing`` adds the empty batch that marks the part complete."""
        if self.closed:
            return
        meta = {"upto_us": str(self.clock() if upto_us is None else upto_us)}
        wrote = bool(self._rows or self._ncols)
        if self._rows:
            unknown = set().union(*self._rows) - self._columns  # iterating a dict: its keys
            if unknown:
                raise TableError(
                    f"table {self.name}: no column {', '.join(sorted(unknown))} (columns: "
                    f"{', '.join(self.schema.names)}); add it to fabric/tables.py")
            batch = self._batch(self._rows)
            self._writer.write_batch(batch, custom_metadata=meta)
            self.rows_written += batch.num_rows
            self._rows.clear()
        if self._ncols:
            batch = self._column_batch(self._cols, self._ncols)
            self._writer.write_batch(batch, custom_metadata=meta)
            self.rows_written += batch.num_rows
            self._cols, self._ncols = {}, 0
        if closing:
            meta["complete"] = "1"
        if closing or not wrote:
            # An empty batch carries the reach when no row does (a table with nothing new
            # since the last flush still says how far it is complete).
            self._writer.write_batch(pa.RecordBatch.from_pylist([], schema=self.schema),
                                     custom_metadata=meta)
        if not closing:
            self._file.flush()  # a streamed part sends the batch now

    def _batch(self, rows: list[dict[str, Any]]) -> pa.RecordBatch:
        """``RecordBatch.from_pylist(rows, schema)``, converted a column at a time (as it does)
        so that a value that does not fit names its column."""
        return self._column_batch({name: [r.get(name) for r in rows] for name in self.schema.names}, len(rows))

    def _column_batch(self, columns: dict[str, list[Any]], n: int) -> pa.RecordBatch:
        """The batch of ``n`` rows given as ``columns`` (a column not given is null)."""
        arrays = []
        for field in self.schema:
            values = columns.get(field.name)
            try:
                arrays.append(pa.nulls(n, field.type) if values is None
                              else pa.array(values, type=field.type))
            except (pa.ArrowInvalid, pa.ArrowTypeError) as exc:
                raise TableError(f"table {self.name}: a row does not fit the columns: column "
                                 f"{field.name} ({field.type}): {exc}") from exc
        return pa.RecordBatch.from_arrays(arrays, schema=self.schema)

    def close(self, upto_us: int | None = None) -> None:
        """Write what is buffered, mark the part complete up to ``upto_us`` (simulated
        microseconds; default: the clock) and close the file; a second call does nothing."""
        if self.closed:
            return
        try:
            self.flush(upto_us, closing=True)
        finally:
            self.closed = True
            self._writer.close()
            self._file.close()

    @property
    def buffered(self) -> int:
        """Rows buffered, not yet written."""
        return len(self._rows) + self._ncols


@dataclass
class PartInfo:
    """What a part file holds: rows readable, simulated time recorded up to, cleanly closed."""

    rows: int = 0
    upto_us: int | None = None
    complete: bool = False
    error: str | None = None


def read_part(path: Path, info: PartInfo | None = None) -> Iterator[pa.RecordBatch]:
    """The non-empty record batches of the part file ``path``, in order; stops quietly at a batch
    cut short (the writer died while writing it). ``info``, if given, is filled in as batches are
    read."""
    info = info if info is not None else PartInfo()
    try:
        reader = pa.ipc.open_stream(pa.memory_map(str(path)))
    except (OSError, pa.ArrowInvalid) as exc:  # died before its schema was on disk
        info.error = f"unreadable: {exc}"
        return
    while True:
        try:
            batch, meta = reader.read_next_batch_with_custom_metadata()
        except StopIteration:
            return
        except (OSError, pa.ArrowInvalid) as exc:
            info.error = f"cut short after {info.rows} rows: {exc}"
            return
        if meta is not None:
            upto = meta.get(b"upto_us")
            if upto is not None:
                info.upto_us = int(upto)
            if meta.get(b"complete") == b"1":
                info.complete = True
        info.rows += batch.num_rows
        if batch.num_rows:
            yield batch


def conform(batch: pa.RecordBatch, schema: pa.Schema) -> pa.RecordBatch:
    """``batch`` with ``schema``'s columns in its order: missing ones null, types cast."""
    cols = []
    for f in schema:
        i = batch.schema.get_field_index(f.name)
        cols.append(pa.nulls(batch.num_rows, f.type) if i < 0 else batch.column(i).cast(f.type))
    return pa.RecordBatch.from_arrays(cols, schema=schema)


MERGE_ROW_GROUP_ROWS = 65_536


def merge_parts(results_dir: Path, table: str, schema: pa.Schema | None = None) -> dict[str, Any]:
    """Merge the part files of ``table`` into ``<results_dir>/<table>.parquet`` (atomically, a
    row group at a time, so memory stays flat), then remove the parts. ``schema``: the merged
    file's columns (default: the table's in ``TABLES``).

    Returns ``{"rows": n, "parts": {federate: {"rows", "upto_s", "complete"[, "error"]}}}``. With no
    part files, an existing merged file is kept (merged before) and a missing one is written
    empty, with the table's columns.
    """
    schema = schema if schema is not None else TABLES[table]
    out = results_dir / f"{table}.parquet"
    parts = sorted((results_dir / "tables").glob(f"{table}-*{PART_SUFFIX}"))
    if not parts and out.exists():
        return {"rows": pq.ParquetFile(out).metadata.num_rows, "parts": {}}
    summary: dict[str, Any] = {"rows": 0, "parts": {}}
    tmp = out.with_suffix(out.suffix + ".tmp")
    out.parent.mkdir(parents=True, exist_ok=True)
    with pq.ParquetWriter(tmp, schema) as writer:
        pending: list[pa.RecordBatch] = []
        pending_rows = 0
        for path in parts:
            info = PartInfo()
            for batch in read_part(path, info):
                pending.append(conform(batch, schema))
                pending_rows += batch.num_rows
                if pending_rows >= MERGE_ROW_GROUP_ROWS:
                    writer.write_table(pa.Table.from_batches(pending, schema=schema))
                    pending, pending_rows = [], 0
            federate = path.name[len(table) + 1:-len(PART_SUFFIX)]
            entry: dict[str, Any] = {
                "rows": info.rows, "complete": info.complete,
                "upto_s": None if info.upto_us is None else info.upto_us / 1e6}
            if info.error:
                entry["error"] = info.error
            summary["parts"][federate] = entry
            summary["rows"] += info.rows
        if pending:
            writer.write_table(pa.Table.from_batches(pending, schema=schema))
    os.replace(tmp, out)
    for path in parts:
        path.unlink(missing_ok=True)
    return summary


def write_table(path: Path, rows: list[dict[str, Any]], schema: pa.Schema | None = None) -> Path:
    """Write ``rows`` (dicts with the same keys) to Parquet at ``path`` atomically, with
    ``schema`` if given (needed for the columns of an empty table); returns ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if rows:
        table = pa.Table.from_pylist(rows, schema=schema)
    else:
        table = schema.empty_table() if schema is not None else pa.table({})
    tmp = path.with_suffix(path.suffix + ".tmp")
    pq.write_table(table, tmp)
    os.replace(tmp, path)
    return path


def read_rows(path: Path) -> list[dict[str, Any]]:
    """All rows of a Parquet file (empty list if the file does not exist)."""
    if not path.exists():
        return []
    return pq.read_table(path).to_pylist()


def write_json(path: Path, data: Any) -> Path:
    """Write ``data`` as indented JSON with sorted keys to ``path`` atomically (a value JSON does
    not know as its ``str``); returns ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=True, default=str) + "\n")
    os.replace(tmp, path)
    return path
