"""Survey correction at scale: many files, or one huge file, corrected in parallel with Dask.

``apply_partitioned(calibration, inputs, output_dir)`` splits the surveys into partitions sized to the cluster --
:data:`TASKS_PER_WORKER` per worker thread, each of :data:`MIN_PARTITION_ROWS` to :data:`MAX_PARTITION_ROWS` rows
(:func:`partition_rows_for`), whatever the files' own row groups -- a CSV into ranges of whole lines (found by one
pass over its bytes), a Parquet file into ranges of rows (consecutive row groups joined, a large one split) -- and
corrects each partition independently in a task of a ``dask.distributed`` cluster: a local one (``workers``
processes) by default, or an existing cluster by its scheduler address. Each task reads its own partition from the
file (only the row groups its rows lie in) through the one reader (the file's own metadata and header first, so the
layout, units and checks are those of the whole file), corrects it block by block with
:func:`magcal.output.apply.correct_block` (the same numbers as ``magcal apply`` on the whole file) and writes its
own ``part-NNNNN.parquet`` (or ``.csv``) in a temporary folder beside ``output_dir``: nothing but the partition's
description goes to the task and its file name and row count come back, so no data pass through the client. The
folder is renamed to ``output_dir`` when every partition is written (a Parquet dataset: ``pyarrow.dataset`` or
``pandas.read_parquet`` read the folder as one table, in order); a bad row, a failed task or Ctrl-C leaves nothing under
the final name. A correction killed outright cannot remove its folder; the next one writing in the same folder does,
once the killed one's process no longer runs, and says so (:func:`remove_stale`; the local cluster's workers end with
the program, as Dask's nannies watch it). The record-only terms are decided once for every file before the tasks start,
as ``magcal apply`` does (:func:`magcal.output.apply.record_choice`: a file of another length than the fitted record,
its rows counted from a Parquet footer or a CSV's line ends, is another record without a row parsed in the client). On a
cluster the input files and the output folder must be on a file system every worker sees.

Messages from a task name the file and the line (CSV: the file's own line numbers, as ``magcal apply`` gives them).
"""

from __future__ import annotations

import io as _io
import logging
import multiprocessing
import os
import re
import shutil
import tempfile
import time
from dataclasses import dataclass, field

import numpy as np

from magcal.calibration.calibration import Calibration
from magcal.core import leftovers
from magcal.core import notes as _notes
from magcal.core.errors import DataWarning, MagcalError, RecordTermWarning
from magcal.core.memory import keep_large_blocks
from magcal.core.notes import Note
from magcal.data.dataset import DatasetError
from magcal.data.io import (
    HEAD_PROBE_BYTES,
    MAX_LINE_BYTES,
    CsvSource,
    ParquetSource,
    check_csv_head,
    check_output_path,
    check_parquet_codec,
    current_umask,
    is_parquet,
    parquet_table,
    parquet_write_options,
    parse_column_mapping,
    write_csv,
)
from magcal.diagnosis import _parallel
from magcal.model import plugins
from magcal.output.apply import (
    AttitudeGaps,
    Refusal,
    _WriteBehind,
    attitude_gap_text,
    correct_block,
    gives_tensor,
    input_columns,
    load_calibration,
    output_columns,
    reads_extras,
    record_choice,
    refuse_non_finite,
    writes_world,
)

#: Rows a task reads, corrects and writes at a time, as ``magcal apply`` does (its ``--chunk-rows``): memory per
#: worker stays bounded whatever the partition's size, and a block's few dozen columns stay in the processor's
#: cache (blocks of 250 000 rows made the correction 6x slower per row than blocks of 20 000 on a busy machine).
BLOCK_ROWS = 20_000
#: Partitions per worker thread: enough that the last ones even out the load, few enough that each task's start
#: (opening the file, its metadata) stays small against its rows.
TASKS_PER_WORKER = 4
#: Bounds on a partition's rows when sized to the workers (:func:`partition_rows_for`).
MIN_PARTITION_ROWS = 20_000
MAX_PARTITION_ROWS = 2_000_000
#: Seconds to wait for a cluster's scheduler.
CONNECT_TIMEOUT_S = 10.0
#: How the local cluster starts its worker processes: forked from a fork server (one per program, which imports
#: dask.distributed and its libraries once; Dask's ``distributed.worker.multiprocessing-method``) where the platform
#: has one, else ``spawn`` (Dask's default: every worker a new interpreter importing them all). On the 2-core
#: development machine (quiet, 2e6 rows of four sensors, Parquet to Parquet, alternating runs): a cluster's first
#: apply in a program 3.2-3.6 s either way, every later one 1.95-2.25 s forked against 3.35-3.8 s spawned (the
#: cluster's start 0.5-0.8 s against 0.9-1.2 s, its close 0.03-0.08 s against 0.3-0.45 s).
LOCAL_START_METHOD = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
#: Modules the local cluster's fork server imports before it forks the workers (:func:`apply_partitioned`):
#: :mod:`magcal.core.leftovers` first, which has the server remove the run folder (the server's socket, the
#: workers' scratch space) as it ends, also after a kill (:func:`magcal.core.leftovers.run_dir`); then what the
#: workers and their tasks import.
FORK_SERVER_MODULES = ("magcal.core.leftovers", "distributed", "pyarrow.parquet", "magcal.output.survey")
#: Local worker processes allowed per CPU core: more only compete for the cores (and thousands exhaust the machine).
WORKERS_PER_CORE = 4


#: A work folder's name: ``.NAME.magcal-HOST-PID-XXXXXXXX.tmp`` beside the output ``NAME``, with six hex digits
#: of the machine's name (:func:`magcal.core.leftovers.host_tag`) and the number of the process that made it, so
#: that the next correction writing beside it removes it once that process no longer runs (:func:`remove_stale`).
WORK_DIR_NAME = re.compile(r"\.(?P<name>.+)\.magcal-(?P<host>[0-9a-f]{6})-(?P<pid>[0-9]+)-[a-z0-9_]{8}\.tmp")


def work_dir_prefix(target: str) -> str:
    """The start of the name of the work folder of a correction into ``target`` (:data:`WORK_DIR_NAME`)."""
    return f".{os.path.basename(target)}.magcal-{leftovers.host_tag()}-{os.getpid()}-"


def remove_stale(directory) -> str | None:
    """Remove the work folders in ``directory`` of corrections whose process no longer runs on this machine (one
    killed outright keeps its partitions there for ever), and the run folders of processes of magcal killed with
    their fork server (:func:`magcal.core.leftovers.remove_stale_run_dirs`); returns the line that says what was
    removed, or None."""
    gone = leftovers.remove_stale(directory, WORK_DIR_NAME, host=leftovers.host_tag())
    work = leftovers.removed_text(gone, "work folder", "parallel correction (magcal apply)")
    runs = leftovers.removed_text(leftovers.remove_stale_run_dirs(), "temporary folder", "run of magcal")
    return "; ".join(x for x in (work, runs) if x) or None


def max_workers() -> int:
    """Most worker processes of a local cluster: :data:`WORKERS_PER_CORE` per CPU core of this machine."""
    return WORKERS_PER_CORE * (os.cpu_count() or 1)


def check_workers(workers) -> int:
    """``workers`` as an int from 1 to :func:`max_workers`, or a :class:`MagcalError` saying the bound."""
    n = int(workers)
    if not 1 <= n <= max_workers():
        raise MagcalError(
            f"--workers {n}: give 1 to {max_workers()} (at most {WORKERS_PER_CORE} per CPU core; this machine has "
            f"{os.cpu_count() or 1}); more processes only compete for the cores. Use --scheduler for a cluster"
        )
    return n


def _distributed():
    try:
        import distributed
    except ImportError:
        raise MagcalError('parallel apply needs dask.distributed: pip install "magcal-workbench[survey]"') from None
    return distributed


def partition_rows_for(total_rows: int, workers: int) -> int:
    """Rows per partition for ``total_rows`` on ``workers`` worker threads: :data:`TASKS_PER_WORKER` partitions per
    worker, within :data:`MIN_PARTITION_ROWS` and :data:`MAX_PARTITION_ROWS`."""
    target = -(-int(total_rows) // max(1, int(workers) * TASKS_PER_WORKER))
    return int(min(MAX_PARTITION_ROWS, max(MIN_PARTITION_ROWS, target)))


@dataclass
class Partition:
    """One piece of one survey file."""

    path: str
    index: int  # the partition's number in the output
    start: int  # CSV: first byte of the data lines; Parquet: first row (0-based)
    stop: int  # CSV: end byte (exclusive); Parquet: end row (exclusive)
    first_line: int  # CSV: line number of the first data line (1-based); Parquet: first row (1-based)
    kind: str  # "csv" or "parquet"

    @property
    def rows(self) -> int | None:
        """Rows of a Parquet partition (None for CSV: known once read)."""
        return self.stop - self.start if self.kind == "parquet" else None


def _too_long(path, line):
    return DatasetError(
        f"{path}: line {line} is longer than {MAX_LINE_BYTES:,} bytes; this is not a CSV of readings (a binary "
        "file, or the line ends are missing): check the file"
    )


def _csv_head(path) -> tuple[bytes, int]:
    """The metadata and header lines of a CSV (bytes) and the byte offset where the data lines begin: the lines up
    to the first that is neither blank nor a ``#`` line, by the reader's own rules (:class:`CsvSource`: a UTF-8
    byte order mark before the first line, any whitespace, a no-break space too, as blank)."""
    head = bytearray()
    with open(path, "rb") as fh:
        check_csv_head(fh.read(HEAD_PROBE_BYTES), path)  # empty, binary, old Mac line ends: the reader's message
        fh.seek(0)
        while True:
            line = fh.readline(MAX_LINE_BYTES + 1)
            if not line:
                break
            if len(line) > MAX_LINE_BYTES:
                raise _too_long(path, head.count(b"\n") + 1)
            text = line.decode("utf-8", "replace")
            if not head:
                text = text.removeprefix("\ufeff")
            head += line
            text = text.strip()
            if text and not text.startswith("#"):
                return bytes(head), len(head)
    raise DatasetError(f"{path}: no header line; see docs/formats.md")


def _line_ends(path, offset, block=1 << 20):
    """Byte positions just after each line end of the file from ``offset`` (and the file's end if the last line
    has none), read block by block; a line over :data:`magcal.data.io.MAX_LINE_BYTES` is refused."""
    with open(path, "rb") as fh:
        fh.seek(offset)
        pos = last = offset
        lines = 0
        while True:
            data = fh.read(block)
            if not data:
                break
            ends = np.flatnonzero(np.frombuffer(data, dtype=np.uint8) == 10) + pos + 1
            starts = np.concatenate([[last], ends[:-1]]) if ends.size else np.array([last])
            if ends.size and np.any(ends - starts > MAX_LINE_BYTES):
                raise _too_long(path, lines + int(np.argmax(ends - starts > MAX_LINE_BYTES)) + 1)
            pos += len(data)
            if ends.size:
                lines += ends.size
                last = int(ends[-1])
                yield ends
            if pos - last > MAX_LINE_BYTES:
                raise _too_long(path, lines + 1)
        if pos > last:
            yield np.array([pos])


#: Most line-end positions :func:`_csv_scan` keeps per file (every ``stride``-th line's; 512 kB).
MAX_LINE_MARKS = 1 << 16


@dataclass
class _CsvScan:
    """One pass over a CSV's data lines: how many, and where every ``stride``-th of them ends."""

    head_lines: int  # lines before the first data line, the header included
    offset: int  # byte where the data lines begin
    lines: int  # data lines (line ends after the head, and a last line without one)
    stride: int  # marks[i] is the byte just after data line (i + 1) * stride
    marks: np.ndarray


def _csv_scan(path) -> _CsvScan:
    """Count a CSV's data lines block by block, keeping the end of every ``stride``-th line: ``stride`` starts at
    1 and doubles (every other mark dropped) whenever more than :data:`MAX_LINE_MARKS` are kept, so a small file
    keeps every line's end and a huge one a bounded sample. Partitions of a multiple of ``stride`` lines are then
    cut from the marks (:func:`_cut_csv`) without a second pass over the bytes."""
    head, offset = _csv_head(path)
    stride, lines, kept = 1, 0, []
    n_kept = 0
    for ends in _line_ends(path, offset):
        first = (-lines - 1) % stride  # the index in ``ends`` of the first line whose number is a multiple
        take = ends[first::stride]
        kept.append(take)
        n_kept += take.size
        lines += ends.size
        while n_kept > MAX_LINE_MARKS:
            marks = np.concatenate(kept)[1::2]  # lines 2s, 4s, ...: the multiples of the doubled stride
            kept, n_kept, stride = [marks], marks.size, 2 * stride
    marks = np.concatenate(kept) if kept else np.zeros(0, dtype=np.int64)
    return _CsvScan(head.count(b"\n"), offset, lines, stride, marks.astype(np.int64))


def _row_groups(path) -> list:
    """Rows of each row group of a Parquet file."""
    import pyarrow.parquet as pq

    try:
        meta = pq.ParquetFile(path).metadata
    except Exception as exc:  # pyarrow's own errors: a damaged or non-Parquet file
        raise DatasetError(f"{path}: not a readable Parquet file ({exc})") from None
    return [meta.row_group(g).num_rows for g in range(meta.num_row_groups)]


def _parquet_ranges(sizes, rows) -> list:
    """Row ranges ``(start, stop)`` of about ``rows`` rows over row groups of ``sizes``: consecutive small groups
    joined (a range ends on a group's edge, so no task reads a group another one reads), a group of more than
    ``1.5 rows`` split evenly."""
    out, start, row = [], 0, 0
    for n in sizes:
        if n > 1.5 * rows:
            if row > start:
                out.append((start, row))
            k = int(round(n / rows))
            edges = [row + (n * j) // k for j in range(k + 1)]
            out += list(zip(edges[:-1], edges[1:]))
            row += n
            start = row
            continue
        if row > start and row + n - start > 1.25 * rows:
            out.append((start, row))
            start = row
        row += n
    if row > start:
        out.append((start, row))
    return out


def partitions(paths, partition_rows: int | None = None, workers: int = 1) -> list[Partition]:
    """The partitions of the survey files, in order (numbered across files).

    ``partition_rows``: rows per partition; by default sized to ``workers`` worker threads over all the files'
    rows (:func:`partition_rows_for`).
    """

    paths = [os.fspath(p) for p in paths]
    for path in paths:
        if not os.path.exists(path):
            raise DatasetError(f"{path}: no such file; check the path")
    groups = {path: _row_groups(path) for path in paths if is_parquet(path)}
    scans: dict = {}
    if partition_rows is None:  # sized from the rows: one pass over each CSV counts them and marks where to cut
        scans = {p: _csv_scan(p) for p in paths if p not in groups}
        total = sum(sum(g) for g in groups.values()) + sum(scan.lines for scan in scans.values())
        partition_rows = partition_rows_for(total, workers)
        stride = max((scan.stride for scan in scans.values()), default=1)
        partition_rows = -(-partition_rows // stride) * stride  # a multiple of every file's marks
    partition_rows = max(1, int(partition_rows))
    out: list = []
    for path in paths:
        if path in groups:
            for start, stop in _parquet_ranges(groups[path], partition_rows):
                out.append(Partition(path, len(out), start, stop, start + 1, "parquet"))
            continue
        if path in scans:
            _cut_csv(path, scans[path], partition_rows, out)
            continue
        head, offset = _csv_head(path)
        line = head.count(b"\n") + 1
        start, n, first = offset, 0, line
        for ends in _line_ends(path, offset):  # memory stays bounded whatever the file holds
            k = 0
            while n + (ends.size - k) >= partition_rows:
                k += partition_rows - n
                pos = int(ends[k - 1])
                out.append(Partition(path, len(out), start, pos, first, "csv"))
                start, first, n = pos, first + partition_rows, 0
            n += ends.size - k
        end = os.path.getsize(path)
        if end > start:
            out.append(Partition(path, len(out), start, end, first, "csv"))
    return out


def _cut_csv(path, scan: _CsvScan, partition_rows: int, out: list) -> None:
    """Append ``path``'s partitions of ``partition_rows`` lines (a multiple of ``scan.stride``) to ``out``, cut at
    the marked line ends: the same partitions as cutting while reading the lines again."""
    step = partition_rows // scan.stride
    start, first = scan.offset, scan.head_lines + 1
    for k in range(step - 1, scan.marks.size, step):
        pos = int(scan.marks[k])
        out.append(Partition(path, len(out), start, pos, first, "csv"))
        start, first = pos, first + partition_rows
    end = os.path.getsize(path)
    if end > start:
        out.append(Partition(path, len(out), start, end, first, "csv"))


def _parquet_part(part: Partition, chunk_rows=BLOCK_ROWS):
    """The file's metadata, the partition's rows as datasets of at most ``chunk_rows`` samples, read from the
    row groups its rows lie in (the rows before its start in its first group are read and skipped), and the
    reader's notes (:attr:`magcal.data.io.ParquetSource.notes`, filled as the rows are read)."""
    src = ParquetSource(part.path)
    meta = src.file.metadata
    edges = np.cumsum([0] + [meta.row_group(g).num_rows for g in range(meta.num_row_groups)])
    groups = [g for g in range(meta.num_row_groups) if edges[g] < part.stop and edges[g + 1] > part.start]

    def chunks():
        if not groups:
            return
        row = int(edges[groups[0]])
        for ds in src.chunks(chunk_rows, groups, row + 1):
            n = ds.n_samples
            lo, hi = max(part.start - row, 0), min(part.stop - row, n)
            row += n
            if hi > lo:
                yield ds if (lo, hi) == (0, n) else ds.subset(np.arange(lo, hi))
            if row >= part.stop:
                return

    return dict(src.metadata), chunks(), src.notes


def _csv_part(part: Partition, columns=None, units=None, drop_bad=False, extras=False):
    """The file's metadata, the partition's rows (a CSV's range of lines) as datasets, read with its head
    (``extras``: its extra channels too, :func:`magcal.output.apply.reads_extras`), and the reader's notes (rows
    dropped...)."""
    head, _ = _csv_head(part.path)
    with open(part.path, "rb") as fh:
        fh.seek(part.start)
        body = fh.read(part.stop - part.start)
    name = f"{part.path} (lines from {part.first_line})"
    with CsvSource(_io.BytesIO(head + body), columns=columns, units=units, name=part.path) as src:
        src.number_lines_from(part.first_line)  # messages name the file's lines
        parts = [c.dataset for c in src.chunks(BLOCK_ROWS, drop_bad=drop_bad, text_columns=extras)]
        meta = dict(src.metadata)
    if not parts:
        raise DatasetError(f"{name}: no data rows")
    return meta, iter(parts), src.notes


def _source_column(name: str, rows: int, fmt: str):
    """The ``source_file`` column of ``rows`` rows: for Parquet a dictionary-encoded Arrow array (one string and
    an index per row; converting a text array to Arrow cost a third of a task's time, 0.35 us a row), for CSV the
    text itself."""
    if fmt != "parquet":
        return np.full(rows, name)
    import pyarrow as pa

    return pa.DictionaryArray.from_arrays(pa.array(np.zeros(rows, np.int32)), pa.array([name]))


def correct_partition(
    calibration_doc: dict,
    part: Partition,
    output_dir: str,
    fmt: str,
    record_choice: str,
    columns=None,
    units=None,
    drop_bad=False,
    uncertainty=False,
    compression=None,
    effects_files=(),
    force=False,
) -> tuple[str, int, int, tuple]:
    """Correct one partition and write it as ``part-NNNNN.<fmt>`` in ``output_dir`` (a Dask task): read from the
    file by the task itself, corrected and written :data:`BLOCK_ROWS` rows at a time (a Parquet row group
    each). ``effects_files``: the user's effect files the calibration's effects come from, loaded in this process
    first (:func:`magcal.model.plugins.load_for_worker`). ``force``: apply the sensors not determined too
    (:class:`magcal.output.apply.Refusal`; by default their columns are left out). Returns the file written, its rows, how many of them
    had no attitude (their world columns NaN), and its reader's notes (:class:`~magcal.core.notes.Note`: rows
    dropped...; a task's warnings would go nowhere the user looks)."""

    keep_large_blocks()  # Dask's MALLOC_TRIM_THRESHOLD_ made every block a fresh mmap
    plugins.load_for_worker(calibration_doc.get("effects") or [], effects_files)  # a user's effects, loaded here
    calibration = Calibration.from_dict(calibration_doc)
    if part.kind == "parquet":
        meta, chunks, said = _parquet_part(part)
    else:
        meta, chunks, said = _csv_part(part, columns, units, drop_bad, extras=reads_extras(calibration))
    tensor = gives_tensor(calibration)
    refusal = Refusal.of(calibration, force)
    meta = {
        **meta,
        **refusal.metadata(),
        "units": "nT",
        "magcal_frame": calibration.frame,
        "magcal_partition": str(part.index),
        "magcal_source": os.path.basename(part.path),
        "magcal_first_row": str(part.first_line),
    }
    out = os.path.join(output_dir, f"part-{part.index:05d}.{fmt}")
    tmp = out + ".tmp"
    rows, writer, behind, blocks, source = 0, None, None, [], None
    gaps = AttitudeGaps()
    terms = calibration.attitude_terms(record_choice)
    try:
        for ds in chunks:
            if rows == 0:
                if ds.n_sensors != calibration.n_sensors:
                    raise MagcalError(
                        f"{part.path}: the survey has {ds.n_sensors} sensor(s) but the calibration is for "
                        f"{calibration.n_sensors}; use the calibration made for this instrument"
                    )
                calibration.check(ds)
                world = writes_world(calibration, ds)
                names = output_columns(calibration.n_sensors, tensor, uncertainty, world, refused=refusal.refused)
            values = correct_block(calibration, ds, record_choice, uncertainty, world, refused=refusal.refused)
            where = f"{part.path} (the partition from row {part.first_line})"
            refuse_non_finite(values, names, where, ds, lambda k, n=rows: f"its row {n + k + 1}")
            if world or terms:
                gaps.add(ds)
            cols = input_columns(part.path, ds, names)
            if source is None or len(source) < ds.n_samples:  # the file's name, made once
                source = _source_column(os.path.basename(part.path), max(ds.n_samples, BLOCK_ROWS), fmt)
            cols["source_file"] = source[: ds.n_samples]
            cols.update({name: values[:, k] for k, name in enumerate(names)})
            rows += ds.n_samples
            if fmt == "parquet":
                import pyarrow.parquet as pq

                table = parquet_table(cols, meta)
                if writer is None:
                    writer = pq.ParquetWriter(tmp, table.schema, **parquet_write_options(table, compression))
                    behind = _WriteBehind()  # encoding, compression and the disk beside the next block's work
                assert behind is not None  # made with the writer
                behind.put(lambda table=table, writer=writer: writer.write_table(table))
            else:
                blocks.append(cols)
        if rows == 0:
            raise DatasetError(f"{part.path} (rows from {part.first_line}): no data rows")
        if writer is not None:
            behind, done = None, behind
            assert done is not None  # made with the writer
            done.close()  # every block written (or the first error raised)
            writer.close()
            writer = None
            os.replace(tmp, out)
        else:
            write_csv(out, {k: np.concatenate([b[k] for b in blocks]) for k in blocks[0]}, metadata=meta)
    finally:
        if behind is not None:  # an error while reading or correcting: stop the writing thread first
            behind.close(raise_error=False)
        if writer is not None:
            writer.close()
        if os.path.exists(tmp):
            os.remove(tmp)
    return out, rows, gaps.missing, tuple(said)


@dataclass
class PartitionedSummary:
    """What :func:`apply_partitioned` did, and what it has to say (``notes``: :class:`~magcal.core.notes.Note` list,
    never raised here: the record-only terms' decisions, a killed run's leftovers removed, rows without
    attitude)."""

    rows: int
    files: list
    seconds: float
    output_dir: str
    scheduler: str
    #: Seconds to start (or reach) the cluster, within ``seconds``.
    start_s: float = 0.0
    #: Worker threads the partitions were sized to, and the partitions.
    workers: int = 1
    partitions: int = 0
    notes: list = field(default_factory=list)

    @property
    def rows_per_s(self) -> float:
        return self.rows / self.seconds if self.seconds > 0 else float("inf")

    @property
    def work_rows_per_s(self) -> float:
        """Rows per second once the cluster runs (its start left out)."""
        work = self.seconds - self.start_s
        return self.rows / work if work > 0 else float("inf")

    def text(self) -> str:
        return (
            f"corrected {self.rows} rows in {self.seconds:.1f} s ({self.rows_per_s:,.0f} rows/s; the cluster's start "
            f"{self.start_s:.1f} s of it) on {self.scheduler}; wrote {len(self.files)} partition(s) to "
            f"{self.output_dir}"
        )


def dask_client(distributed, workers, scheduler):
    """``(client, the local cluster or None, where in words)``: a client of the Dask scheduler at ``scheduler``,
    else of a local cluster of ``workers`` processes of one thread each, started the way that leaves nothing
    behind (its scratch space in the run folder, which goes with the fork server, a kill too)."""
    if scheduler:
        try:
            client = distributed.Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s")
        except (OSError, TimeoutError) as exc:
            raise MagcalError(
                f"--scheduler {scheduler}: cannot reach the Dask scheduler within {CONNECT_TIMEOUT_S:g} s ({exc}); "
                "is it running, and is the address right?"
            ) from None
        return client, None, f"the cluster at {scheduler}"
    import dask

    if LOCAL_START_METHOD == "forkserver":  # one that removes the run folder as it ends, a kill too
        _parallel.start_fork_server(FORK_SERVER_MODULES)
    scratch = {"temporary-directory": leftovers.run_dir()}
    with dask.config.set({"distributed.worker.multiprocessing-method": LOCAL_START_METHOD, **scratch}):
        cluster = distributed.LocalCluster(
            n_workers=int(workers),
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            silence_logs=logging.CRITICAL,  # a task's error reaches the client, said once there
        )
    return distributed.Client(cluster), cluster, f"a local cluster of {int(workers)} worker(s)"


# long: every argument checked before any work, then the Dask run inside one try/finally that owns the
# temporary folder, its clean-up and the publication of the result
def apply_partitioned(
    calibration,
    inputs,
    output_dir,
    fmt: str = "parquet",
    workers: int = 2,
    scheduler=None,
    partition_rows: int | None = None,
    columns=None,
    units=None,
    drop_bad=False,
    record_terms=None,
    progress=None,
    uncertainty=False,
    compression=None,
    force=False,
) -> PartitionedSummary:
    """Correct survey files in parallel on a Dask cluster into a directory of partitions.

    Parameters
    ----------
    calibration : Calibration or str or os.PathLike
    inputs : sequence of str or os.PathLike
        Survey files (CSV or Parquet).
    output_dir : str or os.PathLike
        A new or empty directory; ``part-NNNNN.parquet`` (or ``.csv``) are written, in input order, into a
        temporary folder beside it (``.NAME.magcal-HOST-PID-XXXXXXXX.tmp``, :data:`WORK_DIR_NAME`) that takes its
        name once every partition is written; on any error or interruption the temporary folder is removed and
        ``output_dir`` is left as it was. A work folder there of a correction killed outright (its process no
        longer runs on this machine) is removed first, with a note naming it.
    fmt : {"parquet", "csv"}
    workers : int
        Worker processes of the local cluster, 1 to :func:`max_workers` (ignored with ``scheduler``).
    scheduler : str, optional
        Address of an existing ``dask.distributed`` scheduler (``tcp://host:8786``).
    partition_rows : int, optional
        Rows per partition; by default :data:`TASKS_PER_WORKER` partitions per worker thread of the cluster
        (:func:`partition_rows_for`), whatever the files' row groups.
    columns, units, drop_bad, record_terms, uncertainty, compression, force
        As in :func:`magcal.output.apply.apply_file` (``force``: the sensors not determined are applied too; by
        default their columns are left out of every partition, with a note and a line in each partition's header).
    progress : bool, optional
        A progress bar (tqdm) over the partitions; default when stderr is a terminal.

    Returns
    -------
    PartitionedSummary
    """
    import sys

    t0 = time.perf_counter()
    if fmt not in ("parquet", "csv"):
        raise MagcalError(f"--format {fmt!r}: parquet or csv")

    if compression is not None and fmt != "parquet":
        raise MagcalError(
            f"a compression ({compression!r}) is for Parquet partitions; leave it out with --format {fmt}"
        )
    compression = check_parquet_codec(compression)
    if isinstance(columns, str):
        columns = parse_column_mapping(columns)
    if not scheduler:
        workers = check_workers(workers)
    output_dir = check_output_path(output_dir, "-o", directory=True)  # before any work
    for path in map(os.fspath, inputs):
        if not os.path.isfile(path):
            raise DatasetError(
                f"{path}: " + ("is a directory" if os.path.isdir(path) else "no such file; check the path")
            )
    if not hasattr(calibration, "correct"):
        calibration = load_calibration(calibration)
    refusal = Refusal.of(calibration, force)  # every sensor undetermined: refused before any work
    choices, notes = {}, [refusal.note] if refusal.note else []
    for path in dict.fromkeys(map(os.fspath, inputs)):  # decided once per file, before any task
        choices[path], note = record_choice(calibration, path, record_terms, columns, units, drop_bad)
        if note:
            notes.append(Note(note, RecordTermWarning, "apply"))
    doc = calibration.to_dict()
    # a user's effects live in this process's catalogue only: each task loads their files (the same paths)
    effects_files = tuple(plugins.user_files()) if not all(map(plugins.is_builtin, doc.get("effects") or [])) else ()
    distributed = _distributed()
    progress = sys.stderr.isatty() if progress is None else bool(progress)
    target = os.path.abspath(output_dir)
    removed = remove_stale(os.path.dirname(target))  # a killed correction's partitions, never to be published
    if removed:
        notes.append(Note(removed, UserWarning, "apply"))
    work_dir = tempfile.mkdtemp(prefix=work_dir_prefix(target), suffix=".tmp", dir=os.path.dirname(target))
    cluster = None
    done = False
    t_start = time.perf_counter()
    try:
        client, cluster, where = dask_client(distributed, workers, scheduler)
        start_s = time.perf_counter() - t_start
        try:
            threads = max(1, sum(client.nthreads().values())) if scheduler else int(workers)
            parts = partitions(inputs, partition_rows, threads)
            if not parts:
                raise DatasetError("no data rows in the input files; nothing to correct")
            futures = [
                client.submit(
                    correct_partition,
                    doc,
                    p,
                    work_dir,
                    fmt,
                    choices[os.fspath(p.path)],
                    columns,
                    units,
                    drop_bad,
                    uncertainty,
                    compression,
                    effects_files,
                    force,
                    pure=False,
                )
                for p in parts
            ]
            bar = None
            if progress:
                from tqdm import tqdm

                bar = tqdm(total=len(futures), unit="part", desc="magcal apply", file=sys.stderr, leave=False)
            results = []
            for fut in distributed.as_completed(futures):
                results.append(fut.result())
                if bar is not None:
                    bar.update(1)
            if bar is not None:
                bar.close()
        finally:
            client.close()
        try:
            _publish(work_dir, target)
        except OSError as exc:
            done = True  # every partition is written: keep them where they are
            raise MagcalError(
                f"{target}: cannot give the finished partitions this name ({exc.strerror or exc}); did another "
                f"program create it meanwhile? They are in {work_dir}"
            ) from None
        done = True
    finally:
        if cluster is not None:
            cluster.close()
        if not done:  # a bad row, a failed task, Ctrl-C: no partial output under the final name
            shutil.rmtree(work_dir, ignore_errors=True)
    files = sorted(os.path.join(output_dir, os.path.basename(r[0])) for r in results)
    notes += _notes.unique(n for r in sorted(results, key=lambda r: r[0]) for n in r[3])  # the readers', in file order
    missing = sum(r[2] for r in results)
    if missing:
        tensor = gives_tensor(calibration)
        terms = list(dict.fromkeys(t for c in choices.values() for t in calibration.attitude_terms(c)))
        text = attitude_gap_text(missing, sum(r[1] for r in results), calibration.n_sensors, tensor, terms)
        notes.append(Note(text, DataWarning, "apply"))
    return PartitionedSummary(
        sum(r[1] for r in results),
        files,
        time.perf_counter() - t0,
        output_dir,
        where,
        start_s=start_s,
        workers=threads,
        partitions=len(parts),
        notes=notes,
    )


def _publish(work_dir, target):
    """Give the finished folder of partitions its final name (and the permissions of a folder made by
    ``mkdir``: 0777 less the umask, where ``mkdtemp`` made it 0700)."""
    os.chmod(work_dir, 0o777 & ~current_umask())
    if os.path.isdir(target) and not os.listdir(target):
        os.rmdir(target)  # the empty folder the user named; os.rename replaces only an empty one on POSIX anyway
    os.rename(work_dir, target)
