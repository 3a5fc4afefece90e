"""Records whose attitude has gaps (a live recording's samples before its first ATTITUDE message, a gap in a log)
read, written and fitted as what they are: a sample whose four quaternion cells ``qw, qx, qy, qz`` are all empty
or ``nan`` has no attitude (as a row of NaN Euler angles has none); one with some but not all four, or a zero
quaternion, is refused naming the file, the line (or row) and the column.

Known truth: simulated vehicles (:func:`magcal.data.vehicle.simulate_vehicle`) and a four-sensor array in a site
gradient (:func:`magcal.data.simulation.simulate_timeseries`) whose parameters the tests set.
"""

from __future__ import annotations

import io as _stdio
import os
import tempfile
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magcal.checks.reference import resolve_vector_reference
from magcal.core.errors import DataWarning
from magcal.data import io as mio
from magcal.data.attitude import attitude_present
from magcal.data.dataset import DatasetError
from magcal.data.vehicle import simulate_vehicle, vehicle_truth
from magcal.fitting.vector import fit_vector


def _gappy(n=200, seed=3, runs=((0, 20), (100, 103))):
    """A simulated flight whose attitude is NaN on ``runs`` (0-based half-open), and the gap mask."""
    flight, _ = simulate_vehicle(vehicle_truth(seed=seed), seed=seed, n=n)
    gap = np.zeros(n, bool)
    for a, b in runs:
        gap[a:b] = True
    q = np.array(flight.attitude_wxyz)
    q[gap] = np.nan
    return flight.replace(attitude_wxyz=q), gap


def _read(path, how):
    """The file read by one of the readers' routes: pyarrow's CSV reader (a clean path), the line-by-line reader
    (a file object), small blocks, the Parquet reader."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", DataWarning)  # a gap is no problem: nothing to say
        if how == "path":
            return mio.read_csv(path)
        if how == "file object":
            with open(path, "rb") as fh:
                return mio.read_csv(fh, name=str(path))
        if how == "blocks of 7":
            return mio.read_csv(path, chunk_rows=7, drop_bad=True)  # drop_bad: the line reader, nothing dropped
        return mio.read_parquet(path)


def _same(a, b):
    assert np.array_equal(a.attitude_wxyz, b.attitude_wxyz, equal_nan=True)
    assert np.array_equal(a.readings_nT, b.readings_nT) and np.array_equal(a.time_s, b.time_s)
    for k in b.extra:
        assert np.array_equal(a.extra[k], b.extra[k], equal_nan=True)


# --- reading and writing -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("how", ["path", "file object", "blocks of 7", "parquet"])
def test_a_dataset_with_attitude_gaps_reads_back_equal_from_the_engines_writers(tmp_path, how):
    if how == "parquet":
        pytest.importorskip("pyarrow")
    ds, gap = _gappy()
    path = tmp_path / ("d.parquet" if how == "parquet" else "d.csv")
    (mio.write_parquet if how == "parquet" else mio.write_csv)(path, ds)
    back = _read(path, how)
    _same(back, ds)
    assert np.array_equal(attitude_present(back), ~gap)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.booleans(), min_size=2, max_size=40), st.sampled_from(["csv", "parquet"]))
def test_any_pattern_of_gaps_round_trips(flags, fmt):
    if fmt == "parquet":
        pytest.importorskip("pyarrow")
    gap = np.array(flags, bool)
    flight, _ = simulate_vehicle(vehicle_truth(seed=1), seed=1, n=gap.size)
    q = np.array(flight.attitude_wxyz)
    q[gap] = np.nan
    ds = flight.replace(attitude_wxyz=q)
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, f"d.{fmt}")
        (mio.write_parquet if fmt == "parquet" else mio.write_csv)(path, ds)
        back = mio.read_parquet(path) if fmt == "parquet" else mio.read_csv(path)
    _same(back, ds)


@pytest.mark.parametrize("how", ["path", "file object", "blocks of 7"])
def test_empty_quaternion_cells_mean_no_attitude_as_nan_ones_do(tmp_path, how):
    ds, gap = _gappy(n=60, runs=((0, 5), (30, 33), (59, 60)))
    mio.write_csv(tmp_path / "nan.csv", ds)
    text = (tmp_path / "nan.csv").read_text()
    assert text.count(",nan,nan,nan,nan") == gap.sum()
    blank = text.replace(",nan,nan,nan,nan", ",,,,", 4).replace(",nan,nan,nan,nan", ",NaN, ,nan,", 1)
    (tmp_path / "blank.csv").write_text(blank)
    back = _read(tmp_path / "blank.csv", how)
    _same(back, ds)
    # a DataFrame with missing attitude takes the same reader
    pd = pytest.importorskip("pandas")
    from magcal.data.inputs import as_dataset

    frame = pd.read_csv(_stdio.StringIO(blank), comment="#")
    _same(as_dataset(frame), ds.replace(metadata={}))


def _row_line(path, row):
    """The file's 1-based line of 0-based data row ``row``."""
    lines = path.read_text().splitlines()
    header = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    return header + 2 + row


@pytest.mark.parametrize(
    "missing, named, given_",
    [(["qx"], "qx", "qw, qy, qz hold"), (["qw", "qz"], "qw", "qx, qy hold"), (["qx", "qy", "qz"], "qx", "qw holds")],
)
def test_some_but_not_all_quaternion_cells_missing_is_refused_naming_line_and_column(tmp_path, missing, named, given_):
    ds, gap = _gappy(n=50, runs=((0, 3),))
    cols = mio.dataset_columns(ds)
    cols = {k: np.array(v, dtype=float if k != "group" else None) for k, v in cols.items()}
    for c in missing:
        cols[c][17] = np.nan
    path = tmp_path / "partial.csv"
    mio.write_csv(path, cols, mio.dataset_metadata(ds))
    line = _row_line(path, 17)
    for how in ("path", "file object"):
        with pytest.raises(DatasetError) as err:
            _read(path, how)
        text = str(err.value)
        assert text.startswith(f"{path}: 1 row(s) with bad values: line {line}, column {named}: empty or nan while")
        assert f"{given_} a number; give all four of qw,qx,qy,qz, or leave all four empty" in text
    # --drop-bad drops that row alone, saying so; the rows without attitude stay
    notes = []
    kept = mio.read_csv(path, drop_bad=True, notes=notes)
    assert kept.n_samples == 49 and np.array_equal(attitude_present(kept), ~np.delete(gap, 17))
    assert any(f"dropped 1 row(s) with bad values: line {line}, column {named}" in n.text for n in notes)
    # Parquet: the row (1-based) and the column
    pytest.importorskip("pyarrow")
    mio.write_parquet(tmp_path / "partial.parquet", cols, mio.dataset_metadata(ds))
    with pytest.raises(DatasetError, match=rf"partial\.parquet: row 18, column {named}: empty or nan while"):
        mio.read_parquet(tmp_path / "partial.parquet")


def test_a_zero_or_infinite_quaternion_is_still_refused_and_a_long_one_normalised(tmp_path):
    ds, _ = _gappy(n=30, runs=((0, 2),))
    cols = {k: np.array(v, dtype=float) for k, v in mio.dataset_columns(ds).items()}
    for c in ("qw", "qx", "qy", "qz"):
        cols[c][9] = 0.0
    mio.write_csv(tmp_path / "zero.csv", cols)
    with pytest.raises(DatasetError, match=rf"zero\.csv: line {_row_line(tmp_path / 'zero.csv', 9)}: .* is zero"):
        mio.read_csv(tmp_path / "zero.csv")
    cols["qw"][9], cols["qx"][9] = np.inf, 0.5
    mio.write_csv(tmp_path / "inf.csv", cols)
    with pytest.raises(DatasetError, match=r"column qw: 'inf' is not a finite number"):
        mio.read_csv(tmp_path / "inf.csv")
    cols["qw"][9], cols["qx"][9], cols["qy"][9], cols["qz"][9] = 2.0, 0.0, 0.0, 0.0
    mio.write_csv(tmp_path / "long.csv", cols)
    with pytest.warns(DataWarning, match=r"not unit length \(line \d+: \|q\| = 2\); they are normalised"):
        back = mio.read_csv(tmp_path / "long.csv")
    assert np.allclose(back.attitude_wxyz[9], [1, 0, 0, 0]) and np.isnan(back.attitude_wxyz[:2]).all()


def test_the_vector_fit_of_a_file_with_attitude_gaps_is_the_fit_of_its_samples_with_attitude(tmp_path):
    ds, gap = _gappy(n=1500, seed=9, runs=((0, 150), (700, 720)))
    mio.write_csv(tmp_path / "flight.csv", ds)
    back = mio.read_csv(tmp_path / "flight.csv")
    got = fit_vector(back, resolve_vector_reference(back), terms=[], warn=False)
    clean = ds.subset(~gap)
    ref = fit_vector(clean, resolve_vector_reference(clean), terms=[], warn=False)
    assert np.array_equal(got.fitted, ~gap) and got.gaps.n_without_attitude == 170
    for a, b in zip(got.sensors, ref.sensors):
        assert np.allclose(a.W, b.W, rtol=1e-9) and np.allclose(a.bias_nT, b.bias_nT, atol=1e-6)
