"""Survey correction at scale: many files, or one huge file, corrected in parallel with Dask.

``apply_partitioned(calibration, inputs, output_dir)`` splits the surveys into partitions -- a CSV into ranges of
whole lines (found by one pass over its bytes), a Parquet file into its row groups -- and corrects each partition
independently in a task of a ``dask.distributed`` cluster: a local one (``workers`` processes) by default, or an
existing cluster by its scheduler address. Each task reads its partition through the one reader (the file's own
metadata and header first, so the layout, units and checks are those of the whole file), corrects it with
:func:`magcal.output.apply.correct_block` (the same numbers as ``magcal apply`` on the whole file) and writes
``part-NNNNN.parquet`` (or ``.csv``) in ``output_dir``. The record-only terms are decided once for every file
before the tasks start, as ``magcal apply`` does.

Messages from a task name the file and the line (CSV: counted from the partition's first line, which is given).
"""

from __future__ import annotations

import io as _io
import os
import time
from dataclasses import dataclass

import numpy as np

from magcal.calibration.calibration import Calibration
from magcal.core.errors import MagcalError, RecordTermWarning
from magcal.data.dataset import DatasetError, dataset_columns
from magcal.data.io import (
    CsvSource,
    ParquetSource,
    check_parquet_codec,
    concatenate,
    is_parquet,
    parquet_table,
    parquet_write_options,
    parse_column_mapping,
    write_csv,
)
from magcal.output.apply import correct_block, load_calibration, output_columns, record_choice

#: Default lines (CSV) per partition.
PARTITION_ROWS = 250_000
#: Seconds to wait for a cluster's scheduler.
CONNECT_TIMEOUT_S = 10.0


def _distributed():
    try:
        import distributed
    except ImportError:
        raise MagcalError('parallel apply needs dask.distributed: pip install "magcal-workbench[survey]"') from None
    return distributed


@dataclass
class Partition:
    """One piece of one survey file."""

    path: str
    index: int  # the partition's number in the output
    start: int  # CSV: first byte of the data lines; Parquet: row group
    stop: int  # CSV: end byte (exclusive); Parquet: row group + 1
    first_line: int  # CSV: line number of the first data line (1-based); Parquet: first row (1-based)
    kind: str  # "csv" or "parquet"


def _csv_head(path) -> tuple[bytes, int]:
    """The metadata and header lines of a CSV (bytes) and the byte offset where the data lines begin."""
    head = bytearray()
    with open(path, "rb") as fh:
        for line in fh:
            head += line
            text = line.strip()
            if text and not text.startswith(b"#"):
                return bytes(head), len(head)
    raise DatasetError(f"{path}: no header line; see docs/formats.md")


def partitions(paths, partition_rows: int = PARTITION_ROWS) -> list[Partition]:
    """The partitions of the survey files, in order (numbered across files)."""

    out: list = []
    for path in map(os.fspath, paths):
        if not os.path.exists(path):
            raise DatasetError(f"{path}: no such file; check the path")
        if is_parquet(path):
            import pyarrow.parquet as pq

            meta = pq.ParquetFile(path).metadata
            row = 1
            for g in range(meta.num_row_groups):
                out.append(Partition(path, len(out), g, g + 1, row, "parquet"))
                row += meta.row_group(g).num_rows
            continue
        head, offset = _csv_head(path)
        line = head.count(b"\n") + 1
        with open(path, "rb") as fh:
            fh.seek(offset)
            start, n, first = offset, 0, line
            pos = offset
            for raw in fh:
                pos += len(raw)
                n += 1
                if n == partition_rows:
                    out.append(Partition(path, len(out), start, pos, first, "csv"))
                    start, first, n = pos, first + partition_rows, 0
            if pos > start:
                out.append(Partition(path, len(out), start, pos, first, "csv"))
    return out


def _read_partition(part: Partition, columns=None, units=None, drop_bad=False):
    """The partition as a Dataset (readings in nT), read through the one reader with the file's own head."""
    if part.kind == "parquet":
        src = ParquetSource(part.path)
        return concatenate(list(src.chunks(PARTITION_ROWS, [part.start], part.first_line))), dict(src.metadata)

    head, _ = _csv_head(part.path)
    with open(part.path, "rb") as fh:
        fh.seek(part.start)
        body = fh.read(part.stop - part.start)
    name = f"{part.path} (lines from {part.first_line})"
    with CsvSource(_io.BytesIO(head + body), columns=columns, units=units, name=name) as src:
        parts = [c.dataset for c in src.chunks(PARTITION_ROWS, drop_bad=drop_bad, text_columns=False)]
        meta = dict(src.metadata)
    if not parts:
        raise DatasetError(f"{name}: no data rows")
    return concatenate(parts), meta


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
) -> tuple[str, int]:
    """Correct one partition and write it as ``part-NNNNN.<fmt>`` in ``output_dir`` (a Dask task). Returns the
    file written and its rows."""

    calibration = Calibration.from_dict(calibration_doc)
    ds, meta = _read_partition(part, columns, units, drop_bad)
    if ds.n_sensors != calibration.n_sensors:
        raise MagcalError(
            f"{part.path}: the survey has {ds.n_sensors} sensor(s) but the calibration is for "
            f"{calibration.n_sensors}; use the calibration made for this instrument"
        )
    calibration.check(ds)
    values = correct_block(calibration, ds, record_choice, uncertainty)
    tensor = calibration.n_sensors == 4 and bool(calibration.baseline_m)
    names = output_columns(calibration.n_sensors, tensor, uncertainty)
    cols = dataset_columns(ds)
    cols["source_file"] = np.full(ds.n_samples, os.path.basename(part.path))
    cols.update({name: values[:, k] for k, name in enumerate(names)})
    meta = {
        **meta,
        "units": "nT",
        "magcal_frame": calibration.frame,
        "magcal_partition": str(part.index),
        "magcal_source": os.path.basename(part.path),
        "magcal_first_row": str(part.first_line),
    }
    out = os.path.join(output_dir, f"part-{part.index:05d}.{fmt}")
    tmp = out + ".tmp"
    if fmt == "parquet":
        import pyarrow.parquet as pq

        table = parquet_table(cols, meta)
        pq.write_table(table, tmp, **parquet_write_options(table, compression))
        os.replace(tmp, out)
    else:
        write_csv(out, cols, metadata=meta)
    return out, ds.n_samples


@dataclass
class PartitionedSummary:
    """What :func:`apply_partitioned` did."""

    rows: int
    files: list
    seconds: float
    output_dir: str
    scheduler: str

    @property
    def rows_per_s(self) -> float:
        return self.rows / self.seconds if self.seconds > 0 else float("inf")

    def text(self) -> str:
        return (
            f"corrected {self.rows} rows in {self.seconds:.1f} s ({self.rows_per_s:,.0f} rows/s) on "
            f"{self.scheduler}; wrote {len(self.files)} partition(s) to {self.output_dir}"
        )


def apply_partitioned(
    calibration,
    inputs,
    output_dir,
    fmt: str = "parquet",
    workers: int = 2,
    scheduler=None,
    partition_rows: int = PARTITION_ROWS,
    columns=None,
    units=None,
    drop_bad=False,
    record_terms=None,
    progress=None,
    uncertainty=False,
    compression=None,
) -> PartitionedSummary:
    """Correct survey files in parallel on a Dask cluster into a directory of partitions.

    Parameters
    ----------
    calibration : Calibration or str or os.PathLike
    inputs : sequence of str or os.PathLike
        Survey files (CSV or Parquet).
    output_dir : str or os.PathLike
        A new or empty directory; ``part-NNNNN.parquet`` (or ``.csv``) are written there, in input order.
    fmt : {"parquet", "csv"}
    workers : int
        Worker processes of the local cluster (ignored with ``scheduler``).
    scheduler : str, optional
        Address of an existing ``dask.distributed`` scheduler (``tcp://host:8786``).
    partition_rows : int
        CSV lines per partition (Parquet: one partition per row group).
    columns, units, drop_bad, record_terms, uncertainty, compression
        As in :func:`magcal.output.apply.apply_file`.
    progress : bool, optional
        A progress bar (tqdm) over the partitions; default when stderr is a terminal.

    Returns
    -------
    PartitionedSummary
    """
    import sys
    import warnings

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
    if not hasattr(calibration, "correct"):
        calibration = load_calibration(calibration)
    output_dir = os.fspath(output_dir)
    if os.path.exists(output_dir) and (not os.path.isdir(output_dir) or os.listdir(output_dir)):
        raise MagcalError(
            f"{output_dir}: exists and is not an empty directory; choose a new one (partitions are "
            "never mixed with other files)"
        )
    os.makedirs(output_dir, exist_ok=True)
    parts = partitions(inputs, int(partition_rows))
    if not parts:
        raise DatasetError("no data rows in the input files; nothing to correct")
    choices = {}
    for path in dict.fromkeys(p.path for p in parts):  # decided once per file, before any task
        choices[path], note = record_choice(calibration, path, record_terms, columns, units, drop_bad)
        if note:
            warnings.warn(note, RecordTermWarning, stacklevel=2)
    doc = calibration.to_dict()
    distributed = _distributed()
    progress = sys.stderr.isatty() if progress is None else bool(progress)
    cluster = None
    try:
        if scheduler:
            try:
                client = distributed.Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s")
            except (OSError, TimeoutError) as exc:
                raise MagcalError(
                    f"--scheduler {scheduler}: cannot reach the Dask scheduler within "
                    f"{CONNECT_TIMEOUT_S:g} s ({exc}); is it running, and is the address right?"
                ) from None
            where = f"the cluster at {scheduler}"
        else:
            cluster = distributed.LocalCluster(
                n_workers=int(workers), threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=40
            )
            client = distributed.Client(cluster)
            where = f"a local cluster of {int(workers)} worker(s)"
        try:
            futures = [
                client.submit(
                    correct_partition,
                    doc,
                    p,
                    output_dir,
                    fmt,
                    choices[p.path],
                    columns,
                    units,
                    drop_bad,
                    uncertainty,
                    compression,
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
    finally:
        if cluster is not None:
            cluster.close()
    files = sorted(r[0] for r in results)
    return PartitionedSummary(sum(r[1] for r in results), files, time.perf_counter() - t0, output_dir, where)
