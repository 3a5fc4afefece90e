"""A compensation applied to survey lines in parallel on a Dask cluster: partitions read with a margin of samples.

A compensation's terms are not sample by sample: the eddy terms take each sample's neighbours (the fluxgate's
change per sample, a central difference) and a fitted time offset reads the fluxgate a fraction of a sample later
(linear interpolation between two samples). A partition is therefore read with :func:`margin_samples` rows more on
either side, as Dask's ``map_overlap`` does, compensated whole, and only its own rows are kept: every row's
compensated scalar is the one ``magcal apply`` gives on the whole line, to rounding.

The partitions are those of :mod:`magcal.output.survey` (:func:`magcal.output.survey.partitions`: a CSV cut into
ranges of whole lines, a Parquet file into ranges of rows), each read, compensated and written by its own task as
``part-NNNNN.parquet`` (or ``.csv``) in a temporary folder that takes the output's name once every one is written.
Each part holds the line's columns as magcal reads them (readings in nT) and ``<scalar>_comp``.
"""

from __future__ import annotations

import io as _io
import math
import os
import shutil
import tempfile
import time

import numpy as np

from magcal.core.errors import MagcalError
from magcal.data.dataset import DatasetError, dataset_columns, dataset_metadata
from magcal.data.io import (
    CsvSource,
    ParquetSource,
    check_output_path,
    check_parquet_codec,
    concatenate,
    parquet_table,
    parquet_write_options,
    parse_column_mapping,
    write_csv,
)
from magcal.fitting.compensation import Compensation
from magcal.output.compensated_line import compensated_column, line_mapping, line_record
from magcal.output.survey import (
    BLOCK_ROWS,
    Partition,
    PartitionedSummary,
    _csv_head,
    _distributed,
    _publish,
    check_workers,
    dask_client,
    partitions,
    remove_stale,
    work_dir_prefix,
)

#: Samples read beyond the time offset's reach on either side of a partition: the central difference's one, and
#: the interpolation's and the rounding's, with room to spare.
MARGIN_PAD_SAMPLES = 8

__all__ = ["MARGIN_PAD_SAMPLES", "apply_compensation_partitioned", "compensate_partition", "margin_samples"]


def margin_samples(compensation: Compensation) -> int:
    """Rows read on either side of a partition: the time offset in samples (rounded up) and
    :data:`MARGIN_PAD_SAMPLES`."""
    return int(math.ceil(abs(compensation.time_offset_s) * compensation.sample_rate_hz)) + MARGIN_PAD_SAMPLES


def _newlines(path, lo: int, hi: int) -> np.ndarray:
    """Byte positions of the line ends in ``[lo, hi)`` of a file."""
    with open(path, "rb") as fh:
        fh.seek(lo)
        data = fh.read(hi - lo)
    return np.flatnonzero(np.frombuffer(data, dtype=np.uint8) == 10) + lo


def _lines_before(path, pos: int, lines: int, floor: int, block: int = 1 << 16) -> int:
    """The byte where the ``lines`` lines before ``pos`` (a line's start) begin, not before ``floor``."""
    if lines <= 0:
        return pos
    ends = np.zeros(0, dtype=np.int64)
    lo = pos
    while lo > floor and ends.size <= lines:
        lo = max(floor, lo - block)
        ends = _newlines(path, lo, pos)
    if ends.size <= lines:
        return floor
    return int(ends[-lines - 1]) + 1


def _lines_after(path, pos: int, lines: int, block: int = 1 << 16) -> int:
    """The byte just after the ``lines`` lines from ``pos`` (a line's start), or the file's end."""
    if lines <= 0:
        return pos
    size = os.path.getsize(path)
    hi = pos
    ends = np.zeros(0, dtype=np.int64)
    while hi < size and ends.size < lines:
        hi = min(size, hi + block)
        ends = _newlines(path, pos, hi)
    return size if ends.size < lines else int(ends[lines - 1]) + 1


def _csv_rows(path, head: bytes, lo: int, hi: int, first_line: int, columns, units, drop_bad) -> list:
    """The datasets of a CSV's bytes ``[lo, hi)`` (whole lines), read with its head."""
    if hi <= lo:
        return []
    with open(path, "rb") as fh:
        fh.seek(lo)
        body = fh.read(hi - lo)
    with CsvSource(_io.BytesIO(head + body), columns=columns, units=units, name=path) as src:
        src.number_lines_from(first_line)
        return [c.dataset for c in src.chunks(BLOCK_ROWS, drop_bad=drop_bad, text_columns=True)]


def _csv_with_margin(part: Partition, margin: int, columns, units, drop_bad):
    """(datasets before, the partition's, after) of a CSV partition and ``margin`` lines on either side."""
    head, offset = _csv_head(part.path)
    lo = _lines_before(part.path, part.start, margin, offset)
    hi = _lines_after(part.path, part.stop, margin)
    before_lines = int(_newlines(part.path, lo, part.start).size)
    pieces = [
        _csv_rows(part.path, head, lo, part.start, part.first_line - before_lines, columns, units, drop_bad),
        _csv_rows(part.path, head, part.start, part.stop, part.first_line, columns, units, drop_bad),
    ]
    own_lines = int(_newlines(part.path, part.start, part.stop).size)
    pieces.append(_csv_rows(part.path, head, part.stop, hi, part.first_line + own_lines, columns, units, drop_bad))
    return pieces


def _parquet_with_margin(part: Partition, margin: int, columns):
    """(datasets before, the partition's, after) of a Parquet partition and ``margin`` rows on either side."""
    src = ParquetSource(part.path, columns=columns)
    meta = src.file.metadata
    edges = np.cumsum([0] + [meta.row_group(g).num_rows for g in range(meta.num_row_groups)])
    lo, hi = max(0, part.start - margin), min(int(edges[-1]), part.stop + margin)
    groups = [g for g in range(meta.num_row_groups) if edges[g] < hi and edges[g + 1] > lo]
    row = int(edges[groups[0]]) if groups else 0
    rows = []
    for ds in src.chunks(BLOCK_ROWS, groups, row + 1) if groups else ():
        n = ds.n_samples
        a, b = max(lo - row, 0), min(hi - row, n)
        if b > a:
            rows.append(ds if (a, b) == (0, n) else ds.subset(np.arange(a, b)))
        row += n
        if row >= hi:
            break
    if not rows:
        return [], [], []
    whole = concatenate(rows)
    cuts = (0, part.start - lo, part.stop - lo, whole.n_samples)
    return [[whole.subset(np.arange(a, b))] if b > a else [] for a, b in zip(cuts[:-1], cuts[1:])]


def compensate_partition(
    compensation_doc: dict, part: Partition, output_dir: str, fmt: str, columns=None, units=None, drop_bad=False,
    compression=None,
) -> tuple[str, int]:  # fmt: skip
    """Compensate one partition (a Dask task): read it with :func:`margin_samples` rows on either side, compensate
    the whole, keep its own rows and write them as ``part-NNNNN.<fmt>`` in ``output_dir``. Returns the file and its
    rows."""
    comp = Compensation.from_dict(compensation_doc)
    margin = margin_samples(comp)
    if part.kind == "parquet":
        pieces = _parquet_with_margin(part, margin, columns)
    else:
        pieces = _csv_with_margin(part, margin, columns, units, drop_bad)
    before, own, after = ([d for d in piece if d.n_samples] for piece in pieces)
    if not own:
        raise DatasetError(f"{part.path} (rows from {part.first_line}): no data rows")
    whole = concatenate(before + own + after)
    start = sum(d.n_samples for d in before)
    rows = sum(d.n_samples for d in own)
    values = comp.compensate(line_record(comp, whole))[start : start + rows]
    mine = whole.subset(np.arange(start, start + rows))
    name = compensated_column(comp)
    cols = dict(dataset_columns(mine))
    cols[name] = values
    meta = dataset_metadata(mine) | {
        "magcal_columns": f"readings in nT; {name} the compensated scalar, nT",
        "magcal_partition": str(part.index),
        "magcal_source": os.path.basename(part.path),
        "magcal_first_row": str(part.first_line),
    }
    out = os.path.join(output_dir, f"part-{part.index:05d}.{fmt}")
    if fmt == "parquet":
        import pyarrow.parquet as pq

        table = parquet_table(cols, meta)
        pq.write_table(table, out + ".tmp", **parquet_write_options(table, compression))
        os.replace(out + ".tmp", out)
    else:
        write_csv(out, cols, metadata=meta)
    return out, rows


def apply_compensation_partitioned(
    compensation,
    inputs,
    output_dir,
    fmt: str = "parquet",
    workers: int = 2,
    scheduler=None,
    partition_rows: int | None = None,
    columns=None,
    units=None,
    drop_bad=False,
    compression=None,
) -> PartitionedSummary:
    """Compensate survey lines in parallel on a Dask cluster into a directory of partitions.

    Parameters
    ----------
    compensation : Compensation or str or os.PathLike
        The compensation or its JSON file.
    inputs : sequence of str or os.PathLike
        The lines (CSV or Parquet; the fluxgate found by name as for ``magcal apply``).
    output_dir : str or os.PathLike
        A new or empty directory; the parts are written into a temporary folder beside it that takes its name once
        every part is written (nothing under the name on an error).
    fmt : {"parquet", "csv"}
    workers, scheduler, partition_rows
        As in :func:`magcal.output.survey.apply_partitioned`.
    columns, units, drop_bad, compression
        As in :func:`magcal.output.compensated_line.apply_compensation_file`.

    Returns
    -------
    PartitionedSummary
    """
    t0 = time.perf_counter()
    if fmt not in ("parquet", "csv"):
        raise MagcalError(f"--format {fmt!r}: parquet or csv")
    compression = check_parquet_codec(compression) if fmt == "parquet" else None
    if not scheduler:
        workers = check_workers(workers)
    output_dir = check_output_path(output_dir, "-o", directory=True)
    if not isinstance(compensation, Compensation):
        compensation = Compensation.load(compensation)
    given = parse_column_mapping(columns) if isinstance(columns, str) else columns
    paths = [os.fspath(p) for p in inputs]
    mappings = {path: line_mapping(compensation, path, given) for path in dict.fromkeys(paths)}
    doc = compensation.to_dict()
    distributed = _distributed()
    target = os.path.abspath(output_dir)
    remove_stale(os.path.dirname(target))
    work_dir = tempfile.mkdtemp(prefix=work_dir_prefix(target), suffix=".tmp", dir=os.path.dirname(target))
    cluster, done = None, False
    t_start = time.perf_counter()
    try:
        client, cluster, where = dask_client(distributed, workers, scheduler)
        start_s = time.perf_counter() - t_start
        try:
            threads = max(1, sum(client.nthreads().values())) if scheduler else int(workers)
            parts = partitions(paths, partition_rows, threads)
            if not parts:
                raise DatasetError("no data rows in the input files; nothing to compensate")
            futures = [
                client.submit(
                    compensate_partition,
                    doc,
                    p,
                    work_dir,
                    fmt,
                    mappings[p.path],
                    units,
                    drop_bad,
                    compression,
                    pure=False,
                )  # fmt: skip
                for p in parts
            ]
            results = [fut.result() for fut in distributed.as_completed(futures)]
        finally:
            client.close()
        _publish(work_dir, target)
        done = True
    finally:
        if cluster is not None:
            cluster.close()
        if not done:
            shutil.rmtree(work_dir, ignore_errors=True)
    files = sorted(os.path.join(output_dir, os.path.basename(r[0])) for r in results)
    return PartitionedSummary(
        sum(r[1] for r in results),
        files,
        time.perf_counter() - t0,
        output_dir,
        where,
        start_s=start_s,
        workers=threads,
        partitions=len(parts),
    )
