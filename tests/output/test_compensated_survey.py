"""``magcal apply comp.json LINE --workers N``: a compensation applied on Dask partitions, each read with a margin
of samples on either side (the eddy terms' difference, the time offset's interpolation), gives every row the
compensated scalar of the single-process apply."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from magcal.cli import main
from magcal.data.compensation_flight import CompensationPlatform, simulate_compensation_flight
from magcal.fitting.compensation import CompensationRecord, fit_compensation
from magcal.output.compensated_survey import MARGIN_PAD_SAMPLES, margin_samples

CURRENT = CompensationPlatform(current_nT_per_A=np.array([1.5, -1.0, 0.8]))


def _record(flight):
    return CompensationRecord(
        flight.scalar_nT, flight.flux_nT, flight.sample_rate_hz, current=flight.current_A, current_column="current_A"
    )


@pytest.fixture(scope="module")
def lines(tmp_path_factory):
    """A compensation with eddy terms, a current and the fluxgate 230 ms late, and a line as CSV and Parquet (in
    row groups of 700 rows, so partitions cut through them)."""
    folder = tmp_path_factory.mktemp("lines")
    box = simulate_compensation_flight(1, platform=CURRENT, fluxgate_lag_s=0.23)
    comp = fit_compensation(_record(box), ("current", "time_offset"))
    comp.save(folder / "comp.json")
    line = simulate_compensation_flight(2, platform=CURRENT, fluxgate_lag_s=0.23)
    frame = pd.DataFrame({"t": line.time_s, "x": line.flux_nT[:, 0], "y": line.flux_nT[:, 1]})
    frame = frame.assign(z=line.flux_nT[:, 2], scalar_nT=line.scalar_nT, current_A=line.current_A)
    frame.to_csv(folder / "line.csv", index=False, float_format="%.6f")
    pq.write_table(pa.Table.from_pandas(frame, preserve_index=False), folder / "line.parquet", row_group_size=700)
    return folder, comp


def test_the_margin_covers_the_time_offset(lines):
    _, comp = lines
    assert comp.time_offset_s == pytest.approx(0.23, abs=0.02)
    assert margin_samples(comp) == int(np.ceil(abs(comp.time_offset_s) * 10.0)) + MARGIN_PAD_SAMPLES


@pytest.mark.parametrize(
    ("name", "fmt", "partition_rows"), [("line.csv", "parquet", 997), ("line.parquet", "csv", 1000)]
)
def test_partitions_give_the_single_process_result(lines, tmp_path, capsys, name, fmt, partition_rows):
    folder, _ = lines
    single = tmp_path / "single.parquet"
    assert main(["apply", str(folder / "comp.json"), str(folder / name), "-o", str(single)]) == 0
    out = tmp_path / "parts"
    args = ["apply", str(folder / "comp.json"), str(folder / name), "-o", str(out), "--workers", "2"]
    assert main([*args, "--partition-rows", str(partition_rows), "--format", fmt, "--no-progress"]) == 0
    parts = sorted(out.iterdir())
    assert len(parts) >= 4  # the line cut into several partitions
    read = pd.read_parquet if fmt == "parquet" else (lambda p: pd.read_csv(p, comment="#"))
    together = pd.concat([read(p) for p in parts], ignore_index=True)
    expected = pd.read_parquet(single)
    assert len(together) == len(expected)
    np.testing.assert_allclose(together["t"], expected["t"], atol=1e-9)
    np.testing.assert_allclose(together["scalar_nT_comp"], expected["scalar_nT_comp"], rtol=0, atol=1e-9)
    assert "rows" in capsys.readouterr().out


@pytest.mark.parametrize("margin", ["the compensation's", "none"])
def test_without_the_margin_the_partitions_edges_differ(lines, tmp_path, monkeypatch, margin):
    """The tasks run here, one by one: with the margin every row matches the whole line's compensation; without it
    the rows at the partitions' edges do not (the difference and the offset read past the partition)."""
    from magcal.output import compensated_survey
    from magcal.output.survey import partitions

    folder, comp = lines
    if margin == "none":
        monkeypatch.setattr(compensated_survey, "margin_samples", lambda c: 0)
    parts = partitions([folder / "line.csv"], 500)
    mapping = {"s1x": "x", "s1y": "y", "s1z": "z"}
    files = [
        compensated_survey.compensate_partition(comp.to_dict(), p, str(tmp_path), "parquet", mapping)[0] for p in parts
    ]
    together = pd.concat([pd.read_parquet(f) for f in files], ignore_index=True)
    line = pd.read_csv(folder / "line.csv")
    record = CompensationRecord(
        line["scalar_nT"].to_numpy(), line[["x", "y", "z"]].to_numpy(), 10.0, current=line["current_A"].to_numpy()
    )
    difference = np.abs(together["scalar_nT_comp"].to_numpy() - comp.compensate(record))
    if margin == "none":
        assert difference.max() > 1e-3
    else:
        assert difference.max() < 1e-9
