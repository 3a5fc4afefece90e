"""magcal.data.io: the CSV format of docs/formats.md, column mapping, units, and refusing bad files clearly."""

import os
import re
import warnings
from io import BytesIO, StringIO

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from magcal.core.errors import DataWarning
from magcal.data import io
from magcal.data.dataset import Dataset, DatasetError
from magcal.data.simulation import simulate, simulate_timeseries
from tests.helpers import line_ends


def write(tmp_path, content, name="d.csv"):
    path = tmp_path / name
    path.write_bytes(content.encode("utf-8") if isinstance(content, str) else content)
    return path


def read_quiet(path, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DataWarning)
        return io.read_csv(path, **kw)


# -- round trip ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("n_sensors", [1, 2, 3, 4])
@pytest.mark.parametrize("channels", [(), ("time", "temperature"), ("attitude", "group", "extra", "ref")])
def test_round_trip_is_exact(tmp_path, n_sensors, channels):
    ds = simulate_timeseries("chi2017", n_samples=40, seed=3).sensors(range(n_sensors))
    rng = np.random.default_rng(0)
    changes = {}
    if "time" not in channels:
        changes.update(time_s=None, temperature_C=None)
    if "attitude" not in channels:
        changes["attitude_wxyz"] = None
    if "group" in channels:
        changes["group"] = np.array(["x_up", "y up", "z,up", 'q"x'] * 10)
    if "extra" in channels:
        changes["extra"] = {"lineno": np.arange(40.0), "note": np.array(["a", "b,c"] * 20)}
    if "ref" in channels:
        changes["ref_total_nT"] = 50_000 + rng.normal(0, 5, 40)
    ds = ds.replace(**changes)
    path = tmp_path / "rt.csv"
    io.write_csv(path, ds)
    back = io.read_csv(path)
    assert back.n_sensors == n_sensors and back.n_samples == 40
    np.testing.assert_array_equal(back.readings_nT, ds.readings_nT)
    for attr in ("time_s", "temperature_C", "ref_total_nT", "attitude_wxyz"):
        a, b = getattr(ds, attr), getattr(back, attr)
        assert (a is None) == (b is None), attr
        if a is not None:
            np.testing.assert_array_equal(a, b)
    if ds.group is not None:
        np.testing.assert_array_equal(back.group, ds.group)
    for name, value in ds.extra.items():
        np.testing.assert_array_equal(back.extra[name], value)
    assert back.reference_total_nT == ds.reference_total_nT and back.noise_nT == ds.noise_nT
    assert back.source == str(path)


def test_metadata_keys_all_kept_and_numbers_parsed(tmp_path):
    path = write(
        tmp_path,
        "# site: range B: north pad\n# comment without colon\n# baseline_m: 0.25\n"
        "# reference_total_nT: 52193\n# noise_nT: 0.5\n# operator: A. N. Other\ns1x,s1y,s1z\n"
        "50000,1,2\n",
    )
    ds = read_quiet(path)
    assert ds.metadata["site"] == "range B: north pad" and ds.metadata["operator"] == "A. N. Other"
    assert ds.baseline_m == 0.25 and ds.reference_total_nT == 52193.0 and ds.noise_nT == 0.5


def test_bare_xyz_is_one_sensor_and_unknown_columns_are_kept(tmp_path):
    path = write(tmp_path, "x,y,z,heading,status\n30000,20000,30000,12.5,ok\n30010,20010,30020,13.0,bad\n")
    ds = io.read_csv(path)
    assert ds.n_sensors == 1
    np.testing.assert_array_equal(ds.readings_nT[0, 1], [30010, 20010, 30020])
    np.testing.assert_array_equal(ds.extra["heading"], [12.5, 13.0])
    assert list(ds.extra["status"]) == ["ok", "bad"]


def test_bom_crlf_blank_lines_and_spaces_are_fine(tmp_path):
    path = write(
        tmp_path, "\ufeff# units: nT\r\n\r\n s1x , s1y ,s1z\r\n30000, 20000 ,30000\r\n\r\n30001,20001,30001\r\n"
    )
    ds = io.read_csv(path)
    np.testing.assert_array_equal(ds.readings_nT[0], [[30000, 20000, 30000], [30001, 20001, 30001]])


# -- units --------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("unit,factor", [("nT", 1.0), ("uT", 1e3), ("µT", 1e3), ("G", 1e5), ("mG", 1e2)])
@pytest.mark.parametrize("where", ["metadata", "argument"])
def test_units_are_converted_to_nT(tmp_path, unit, factor, where):
    ds = simulate("chi2017", n_samples=20, seed=1).sensors([0])
    raw = ds.readings_nT[0] / factor
    head = f"# units: {unit}\n" if where == "metadata" else ""
    body = "\n".join(",".join(repr(float(v)) for v in row) for row in raw)
    path = write(tmp_path, head + "x,y,z\n" + body + "\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error", DataWarning)  # correct units: no sanity warning
        back = io.read_csv(path, units=unit if where == "argument" else None)
    np.testing.assert_allclose(back.readings_nT[0], ds.readings_nT[0], rtol=1e-12)


@pytest.mark.parametrize("true_unit,factor", [("uT", 1e3), ("G", 1e5), ("mG", 1e2)])
def test_readings_in_another_unit_give_a_warning_naming_it(tmp_path, true_unit, factor):
    raw = simulate("chi2017", n_samples=20, seed=1).readings_nT[0] / factor
    body = "\n".join(",".join(repr(float(v)) for v in row) for row in raw)
    path = write(tmp_path, "x,y,z\n" + body + "\n")
    with pytest.warns(DataWarning, match=f"look like {true_unit}"):
        io.read_csv(path)


def test_units_argument_overrides_the_file_with_a_warning(tmp_path):
    path = write(tmp_path, "# units: nT\nx,y,z\n30,20,30\n31,21,30\n")
    with pytest.warns(DataWarning, match="overrides"):
        ds = io.read_csv(path, units="uT")
    assert ds.readings_nT[0, 0, 0] == 30_000.0


# -- raw counts with an LSB ---------------------------------------------------------------------------------------
def counts_file(tmp_path, head, lsb_nT=150.0, seed=1):
    """A one-sensor file of integer counts of ``lsb_nT``; returns (path, the readings in nT)."""
    ds = simulate("chi2017", n_samples=30, seed=seed).sensors([0])
    counts = np.round(ds.readings_nT[0] / lsb_nT).astype(int)
    body = "\n".join(",".join(str(v) for v in row) for row in counts)
    return write(tmp_path, head + "x,y,z\n" + body + "\n"), counts * lsb_nT


@pytest.mark.parametrize(
    "head,kw",
    [
        ("# units: counts\n# lsb_nT: 150\n", {}),
        ("# lsb_nT: 150\n# units: counts\n", {}),  # order of the lines does not matter
        ("# units: counts\n", {"lsb_nT": 150.0}),
        ("", {"units": "counts", "lsb_nT": "150"}),
        ("# units: counts\n# lsb_nT: 15\n", {"lsb_nT": 150.0}),  # --lsb overrides (with a warning)
        ("# units: uT\n", {"units": "counts", "lsb_nT": 150.0}),  # --units counts overrides (with a warning)
    ],
)
def test_raw_counts_are_read_with_their_lsb(tmp_path, head, kw):
    path, truth_nT = counts_file(tmp_path, head)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ds = io.read_csv(path, **kw)
    np.testing.assert_allclose(ds.readings_nT[0], truth_nT, rtol=1e-12)
    assert float(ds.metadata["lsb_nT"]) == 150.0  # kept for the quality report and written back
    overrides = [str(w.message) for w in caught]
    assert len(overrides) == ("lsb_nT: 15\n" in head or "uT" in head), overrides
    assert all("overrides" in m for m in overrides)


@pytest.mark.parametrize(
    "head,kw,needles",
    [
        ("# units: counts\n", {}, ["line 1", "metadata units", "--lsb", "lsb_nT"]),
        ("", {"units": "counts"}, ["--units counts", "--lsb NT_PER_COUNT"]),
        ("", {"lsb_nT": 150.0}, ["--lsb 150", "raw counts", "--units counts"]),
        ("# units: uT\n", {"lsb_nT": 150.0}, ["--lsb 150", "in uT", "units line"]),
        ("# units: counts\n# lsb_nT: zero\n", {}, ["line 2", "lsb_nT", "positive number of nT per count"]),
        ("# units: counts\n", {"lsb_nT": "-2"}, ["--lsb", "'-2'", "positive number"]),
    ],
)
def test_counts_without_a_valid_lsb_are_refused_clearly(tmp_path, head, kw, needles):
    path, _ = counts_file(tmp_path, head)
    with pytest.raises(DatasetError) as err:
        read_quiet(path, **kw)
    for needle in needles:
        assert needle in str(err.value), str(err.value)
    assert str(path) in str(err.value) or "--lsb" in str(err.value)


@pytest.mark.parametrize("true_lsb,given_lsb,warned", [(150.0, 150.0, False), (150.0, 15.0, True), (15.0, 150.0, True)])
def test_a_wrong_lsb_gives_a_warning_with_the_lsb_that_fits(tmp_path, true_lsb, given_lsb, warned):
    path, _ = counts_file(tmp_path, "# units: counts\n", lsb_nT=true_lsb)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        io.read_csv(path, lsb_nT=given_lsb)
    messages = [str(w.message) for w in caught]
    assert bool(messages) == warned, messages
    if warned:
        assert "check the LSB" in messages[0]
        suggested = float(re.search(r"about ([0-9.e+-]+) nT per count", messages[0]).group(1))
        assert suggested == pytest.approx(true_lsb, rel=0.05)


def test_counts_round_trip_as_nT_with_the_lsb_kept(tmp_path):
    path, truth_nT = counts_file(tmp_path, "# units: counts\n# lsb_nT: 150\n")
    ds = io.read_csv(path)
    out = tmp_path / "back.csv"
    io.write_csv(out, ds)
    back = io.read_csv(out)  # units: nT now; the lsb_nT line is only information
    np.testing.assert_array_equal(back.readings_nT, ds.readings_nT)
    assert back.metadata["units"] == "nT" and back.metadata["lsb_nT"] == "150"


# -- column mapping -----------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "mapping",
    [
        {"s1x": "magX", "s1y": "magY", "s1z": "magZ", "t": "time"},
        {"x": "magX", "y": "magY", "z": "magZ", "t": "time"},
        "x=magX, y=magY, z=magZ, t=time",
    ],
)
def test_column_mapping(tmp_path, mapping):
    path = write(tmp_path, "time,magZ,magX,magY,t\n0.5,30,10,20,zzz\n1.5,31,11,21,yyy\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error", DataWarning)
        ds = io.read_csv(path, columns=mapping, units="uT")
    np.testing.assert_array_equal(ds.readings_nT[0], [[10000, 20000, 30000], [11000, 21000, 31000]])
    np.testing.assert_array_equal(ds.time_s, [0.5, 1.5])
    assert list(ds.extra["t"]) == ["zzz", "yyy"]  # the file's own 't' is kept, not used


@pytest.mark.parametrize(
    "mapping,match",
    [
        ({"x": "nope", "y": "b", "z": "c"}, "nope.*no such column"),
        ({"w": "a"}, "not a magcal column"),
        ("x=a,y", "not of the form"),
        ({"x": "a", "y": "a", "z": "c"}, "more than one"),
    ],
)
def test_bad_column_mapping_is_refused(tmp_path, mapping, match):
    path = write(tmp_path, "a,b,c\n1,2,3\n")
    with pytest.raises(DatasetError, match=match):
        io.read_csv(path, columns=mapping)


# -- refusals -----------------------------------------------------------------------------------------------------
BAD_FILES = [
    ("empty", b"", ["empty"]),
    ("blank", b"\n\n  \n", ["empty"]),
    ("only metadata", b"# units: nT\n# baseline_m: 0.5\n", ["no header"]),
    ("binary", bytes(range(256)) * 4, ["binary"]),
    ("not utf-8", "# units: nT\nx,y,z\n1,2,3\n\xe9,2,3\n".encode("latin-1"), ["line 4", "UTF-8"]),
    ("no header", b"1,2,3\n4,5,6\n", ["line 1", "header"]),
    ("no sensor columns", b"a,b,c\n1,2,3\n", ["no magnetometer columns", "a, b, c"]),
    ("missing axis", b"s1x,s1y,t\n1,2,3\n", ["sensor 1", "s1z"]),
    ("sensor gap", b"s1x,s1y,s1z,s3x,s3y,s3z\n1,2,3,4,5,6\n", ["not for 2"]),
    ("partial quaternion", b"x,y,z,qw,qx\n1,2,3,1,0\n", ["qw,qx,qy,qz"]),
    ("duplicate column", b"x,y,z,y\n1,2,3,4\n", ["line 1", "'y' appears twice"]),
    ("ragged short", b"x,y,z\n1,2,3\n4,5\n", ["line 3", "2 field"]),
    ("ragged long", b"x,y,z\n1,2,3\n4,5,6,7\n", ["line 3", "4 field"]),
    ("text value", b"# units: nT\nx,y,z\n1,2,3\n4,five,6\n", ["line 4", "column s1y", "'five'"]),
    ("nan", b"x,y,z\n1,2,3\n4,5,nan\n", ["line 3", "column s1z", "finite"]),
    ("inf", b"x,y,z\n1,2,3\n-inf,5,6\n", ["line 3", "column s1x"]),
    ("empty cell", b"x,y,z,temp\n1,2,3,20\n4,5,6,\n", ["line 3", "column temp", "empty"]),
    ("repeated time", b"t,x,y,z\n0,1,2,3\n1,1,2,3\n1,1,2,3\n", ["line 4", "column t", "repeats", "line 3"]),
    ("time going back", b"t,x,y,z\n0,1,2,3\n2,1,2,3\n1,1,2,3\n", ["line 4", "goes back", "line 3"]),
    ("no rows", b"x,y,z\n", ["no data rows"]),
    ("bad baseline", b"# baseline_m: -0.5\nx,y,z\n1,2,3\n", ["line 1", "baseline_m"]),
    ("bad reference", b"# reference_total_nT: lots\nx,y,z\n1,2,3\n", ["reference_total_nT"]),
    ("unknown unit", b"# units: furlongs\nx,y,z\n1,2,3\n", ["unknown unit", "furlongs"]),
    ("zero quaternion", b"x,y,z,qw,qx,qy,qz\n1,2,3,0,0,0,0\n", ["line 2", "zero"]),
    ("lone CR", b"x,y,z\r1,2,3\r4,5,6\r", ["carriage return"]),
    ("quote over lines", b'x,y,z,note\n1,2,3,a\n1,2,3,"b\nc"\n4,5,6,d\n', ["line 3", "quoted field", "one line"]),
    ("sensor 5", b"s1x,s1y,s1z,s5x,s5y,s5z\n1,2,3,4,5,6\n", ["sensor"]),
]


@pytest.mark.parametrize("name,content,needles", BAD_FILES, ids=[b[0] for b in BAD_FILES])
def test_bad_files_are_refused_with_a_clear_message(tmp_path, name, content, needles):
    path = write(tmp_path, content)
    with pytest.raises(DatasetError) as info:
        read_quiet(path)
    message = str(info.value)
    assert str(path) in message
    for needle in needles:
        assert needle.lower() in message.lower(), (needle, message)


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(DatasetError, match="no such file"):
        io.read_csv(tmp_path / "absent.csv")
    with pytest.raises(DatasetError, match="directory"):
        io.read_csv(tmp_path)


def test_line_numbers_count_metadata_and_blank_lines(tmp_path):
    lines = ["# a: 1", "# b: 2", "", "x,y,z", "1,2,3", "", "4,5,6", "7,oops,9", "10,11,12"]
    path = write(tmp_path, "\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match="line 8, column s1y"):
        io.read_csv(path)


def test_drop_bad_drops_exactly_the_bad_rows_and_names_them(tmp_path):
    rows = ["30000,20000,30000"] * 10
    rows[2] = "30000,nan,30000"
    rows[5] = "30000,,30000"
    rows[7] = "abc,1,2"
    path = write(tmp_path, "x,y,z\n" + "\n".join(rows) + "\n")
    with pytest.raises(DatasetError, match="3 row"):
        io.read_csv(path)
    with pytest.warns(DataWarning, match=r"dropped 3 row.*line 4.*line 7.*line 9"):
        ds = io.read_csv(path, drop_bad=True)
    assert ds.n_samples == 7


def test_all_rows_bad_under_drop_bad_is_an_error(tmp_path):
    path = write(tmp_path, "x,y,z\nnan,1,2\n1,inf,2\n")
    with pytest.raises(DatasetError, match="no data rows|0 sample"):
        read_quiet(path, drop_bad=True)


def test_too_few_samples(tmp_path):
    path = write(tmp_path, "x,y,z\n30000,20000,30000\n30001,20000,30000\n")
    with pytest.raises(DatasetError, match="2 sample.*5 needed"):
        read_quiet(path, min_samples=5)
    ds = read_quiet(path)
    with pytest.raises(DatasetError, match="too few"):
        io.require_samples(ds, 9, "bias, scale and non-orthogonality")


@pytest.mark.parametrize("chunk_rows", [1, 3, 7, 1000])
def test_chunked_reading_matches_and_checks_time_across_chunks(tmp_path, chunk_rows):
    ds = simulate_timeseries("chi2017", n_samples=25, seed=2)
    path = tmp_path / "c.csv"
    io.write_csv(path, ds)
    back = io.read_csv(path, chunk_rows=chunk_rows)
    np.testing.assert_array_equal(back.readings_nT, ds.readings_nT)
    np.testing.assert_array_equal(back.time_s, ds.time_s)
    text = path.read_text().splitlines()
    header_at = next(i for i, line in enumerate(text) if not line.startswith("#"))
    k = header_at + 11  # 0-based index of the 11th data row; copy the time of the row before it
    prev_t = text[k - 1].split(",")[0]
    text[k] = ",".join([prev_t] + text[k].split(",")[1:])
    path.write_text("\n".join(text) + "\n")
    with pytest.raises(DatasetError, match=f"line {k + 1}, column t.*repeats.*line {k}"):
        io.read_csv(path, chunk_rows=chunk_rows)


# -- writing ------------------------------------------------------------------------------------------------------
def test_write_columns_mapping_and_float_format(tmp_path):
    path = tmp_path / "m.csv"
    io.write_csv(
        path,
        {"x": [1.0, 2.5], "y": [3, 4], "z": [5.0, 6.0], "label": ["a", "b,c"]},
        metadata={"units": "uT", "note": "two\nlines"},
        float_format="%.2f",
    )
    text = path.read_text()
    assert text.startswith("# units: uT\n# note: two lines\nx,y,z,label\n1.00,3.00,5.00,a\n")
    ds = read_quiet(path)
    assert ds.readings_nT[0, 1, 0] == 2500.0 and list(ds.extra["label"]) == ["a", "b,c"]


def test_write_is_atomic(tmp_path):
    path = tmp_path / "keep.csv"
    path.write_text("precious\n")
    with pytest.raises(DatasetError, match="different lengths"):
        io.write_csv(path, {"x": [1, 2], "y": [1]})
    assert path.read_text() == "precious\n"

    class Boom(Exception):
        pass

    with pytest.raises(Boom):
        with io.atomic_write(path) as fh:
            fh.write("half a file")
            raise Boom()
    assert path.read_text() == "precious\n"
    assert os.listdir(tmp_path) == ["keep.csv"]  # no temporary file left behind


# -- property tests: any input gives a Dataset or a clean DatasetError -----------------------------------------------
def _read_any(tmp_path, data):
    path = tmp_path / "fuzz.csv"
    path.write_bytes(data)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DataWarning)
            ds = io.read_csv(path)
    except DatasetError as exc:
        assert str(exc) and str(path) in str(exc)
        return None
    assert isinstance(ds, Dataset) and ds.n_samples >= 1
    assert np.all(np.isfinite(ds.readings_nT))
    return ds


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.binary(max_size=400))
def test_any_bytes_give_a_dataset_or_a_clean_error(tmp_path, data):
    _read_any(tmp_path, data)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.text(max_size=300))
def test_any_text_gives_a_dataset_or_a_clean_error(tmp_path, text):
    _read_any(tmp_path, text.encode("utf-8"))


CELLS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-(10**6), 10**6).map(str),
    st.sampled_from(["", " ", "nan", "NaN", "inf", "-", "1e400", "1_000", '"', '"1,2"', "x", "0x10", "١٢", "\t5"]),
)
HEADERS = st.lists(
    st.sampled_from(
        [
            "x",
            "y",
            "z",
            "s1x",
            "s1y",
            "s1z",
            "s2x",
            "s2y",
            "s2z",
            "t",
            "temp",
            "group",
            "ref_total",
            "qw",
            "qx",
            "qy",
            "qz",
            "other",
            "",
        ]
    ),
    min_size=1,
    max_size=8,
)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    HEADERS,
    st.lists(st.lists(CELLS, min_size=0, max_size=9), max_size=8),
    st.lists(st.sampled_from(["# units: uT", "# baseline_m: 0.5", "# noise_nT: x", "#", "# units: bogus"]), max_size=3),
)
def test_structured_fuzz_gives_a_dataset_or_a_clean_error(tmp_path, header, rows, meta):
    text = "\n".join(meta + [",".join(header)] + [",".join(r) for r in rows]) + "\n"
    ds = _read_any(tmp_path, text.encode("utf-8"))
    if ds is not None:  # what was accepted is what the file said
        assert ds.n_samples == len(rows)


@pytest.mark.parametrize("units, factor, warned", [("nT", 1.0, False), ("nT", 1e-3, True)])
def test_units_check_looks_past_a_hard_iron_offset(units, factor, warned):
    """An offset larger than the field (MEMS on a platform) is not a unit error, and uT is still caught."""
    import warnings

    from magcal.data.simulation import simulate

    ds = simulate("chi2017", n_samples=200, seed=2)
    shifted = ds.replace(readings_nT=(ds.readings_nT + np.array([90_000.0, 60_000.0, -30_000.0])) * factor)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # check_units says, never warns: the readers put its text in their notes
        text = io.check_units(shifted, units)
    assert (text is not None) == warned, text
    if warned:
        assert "--units uT" in text


# -- file objects (an upload's bytes, text in memory, an open file) ----------------------------------------------------
FILE_OBJECTS = {
    "BytesIO": lambda path: BytesIO(path.read_bytes()),
    "StringIO": lambda path: StringIO(path.read_text(encoding="utf-8")),
    "binary file": lambda path: open(path, "rb"),
    "text file": lambda path: open(path, encoding="utf-8", newline=""),
}


@pytest.mark.parametrize("kind", FILE_OBJECTS)
def test_a_file_object_reads_as_its_path_does(tmp_path, monkeypatch, kind):
    ds = simulate_timeseries("chi2017", n_samples=300, seed=4)  # longer than the 8 kB probe
    path = tmp_path / "rt.csv"
    io.write_csv(path, ds, metadata={"site": "pad B"})
    monkeypatch.setattr(io._FileLines, "_BLOCK", 7)  # lines cross the blocks the file object is read in
    with FILE_OBJECTS[kind](path) as fh:
        back = io.read_csv(fh, name="upload.csv", chunk_rows=64)
        assert not fh.closed  # the caller's file is left open
    ref = io.read_csv(path)
    assert back.source == "upload.csv" and back.metadata == ref.metadata
    for attr in ("readings_nT", "time_s", "temperature_C", "attitude_wxyz"):
        np.testing.assert_array_equal(getattr(back, attr), getattr(ref, attr))


def test_a_file_object_is_named_by_name_then_its_own_name(tmp_path):
    path = write(tmp_path, "x,y,z\n50000,1,2\n")
    with open(path, "rb") as fh:
        assert read_quiet(fh).source == str(path)
    assert read_quiet(BytesIO(path.read_bytes())).source == "<file object>"


@pytest.mark.parametrize("name,content,needles", BAD_FILES, ids=[b[0] for b in BAD_FILES])
def test_a_bad_file_object_gives_the_paths_message_with_the_name_given(tmp_path, name, content, needles):
    path = write(tmp_path, content)
    with pytest.raises(DatasetError) as from_path:
        read_quiet(path)
    with pytest.raises(DatasetError) as from_bytes:
        read_quiet(BytesIO(content), name="upload.csv")
    assert str(from_bytes.value) == str(from_path.value).replace(str(path), "upload.csv")


def test_a_text_file_in_the_wrong_encoding_is_a_clean_error(tmp_path):
    path = write(tmp_path, "x,y,z\n50000,1,2\n50001,1,2 \u00b5T\n")
    with open(path, encoding="ascii") as fh, pytest.raises(DatasetError, match="^upload.csv: .*UTF-8"):
        read_quiet(fh, name="upload.csv")


def test_a_clean_file_is_read_by_pyarrow_with_the_same_result(tmp_path, monkeypatch):
    """The whole-file fast path (pyarrow's CSV reader feeding the same dataset builder) gives exactly the
    line-by-line reader's dataset; a file with a problem still gets the line-by-line reader's precise message."""
    pytest.importorskip("pyarrow")
    mio = io
    ds = simulate_timeseries("chi2017", n_samples=400, seed=3, rate_hz=5.0)
    path = tmp_path / "clean.csv"
    mio.write_csv(path, ds)
    text = path.read_text().replace("t,s1x", "site,t,s1x", 1)
    lines = text.splitlines()
    head = [i for i, line in enumerate(lines) if line.startswith("site,")][0]
    lines = lines[: head + 1] + [f"B{i % 3}," + line for i, line in enumerate(lines[head + 1 :])]
    path.write_text("\n".join(lines) + "\n")
    with mio.CsvSource(path) as src:
        slow = mio.concatenate([c.dataset for c in src.chunks(150)])
    fast = mio._read_csv_arrow(path, None, None, None, None)
    assert fast is not None
    np.testing.assert_array_equal(fast.readings_nT, slow.readings_nT)
    np.testing.assert_array_equal(fast.time_s, slow.time_s)
    np.testing.assert_array_equal(fast.temperature_C, slow.temperature_C)
    np.testing.assert_array_equal(fast.attitude_wxyz, slow.attitude_wxyz)
    assert fast.metadata == slow.metadata and list(fast.extra["site"]) == list(slow.extra["site"])
    # read_csv takes the fast path for it: the line-by-line chunks are never asked for
    monkeypatch.setattr(mio.CsvSource, "chunks", lambda *a, **k: (_ for _ in ()).throw(AssertionError("slow")))
    assert mio.read_csv(path).n_samples == 400
    monkeypatch.undo()
    bad = tmp_path / "bad.csv"
    lines[head + 60] = lines[head + 60].replace(",", ",x", 3)
    bad.write_text("\n".join(lines) + "\n")
    assert mio._read_csv_arrow(bad, None, None, None, None) is None
    with pytest.raises(mio.DatasetError, match=rf"line {head + 61}"):
        mio.read_csv(bad)


# -- a CSV's rows counted from its bytes (CsvSource.count_rows), and runs of blank lines -----------------------------
def test_space_lead_bytes_are_the_first_bytes_of_every_whitespace_character():
    """A line that begins with none of these bytes holds more than whitespace: the count decodes no other line."""
    firsts = {chr(c).encode("utf-8", "surrogatepass")[0] for c in range(0x110000) if chr(c).isspace()}
    assert set(io.SPACE_LEAD_BYTES) == firsts
    for b in range(256):  # the search for a line that may be blank finds exactly these after a line end
        assert (io._MAYBE_BLANK.search(b"1,2\n" + bytes([b]) + b"3") is not None) == (b in firsts), b


#: Lines the reader skips as blank (``str.strip`` empty), and what may stand before a row's first digit.
BLANK_LINES = ["", " ", "\t", " \t  ", "\r", "\x0b", "\x0c", "\x1c", "\x85", "\xa0", "\u2028", "\u3000", " \xa0\t"]
ROW_LEADS = ["", "", " ", "\t", "\xa0", "\u3000"]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    head=st.lists(st.sampled_from(["# units: nT", "#", "# operator: a", "", "  ", "\t"]), max_size=4),
    body=st.lists(
        st.one_of(
            st.tuples(st.just("row"), st.sampled_from(ROW_LEADS)),
            st.tuples(st.just("blank"), st.sampled_from(BLANK_LINES)),
        ),
        max_size=40,
    ),
    crlf=st.lists(st.booleans(), min_size=45, max_size=45),
    last_end=st.booleans(),
    bom=st.booleans(),
    block=st.integers(1, 40),
    chunk_rows=st.integers(1, 6),
)
def test_the_row_count_is_the_readers_number_of_samples(tmp_path, head, body, crlf, last_end, bom, block, chunk_rows):
    """Comment, metadata and blank lines before the header; blank lines of any whitespace, rows that begin with
    whitespace, LF or CRLF line by line, a last line with or without its end, a BOM, the count's blocks cutting
    lines anywhere: the count is the samples the reader yields (in blocks of any size), without parsing a row."""
    lines = [*head, "s1x,s1y,s1z"]
    rows = 0
    for kind, text in body:
        if kind == "row":
            rows += 1
            text = f"{text}{rows},{2 * rows}.5,-{rows}e2"
        lines.append(text)
    ends = ["\r\n" if c else "\n" for c in crlf[: len(lines)]]
    text = "".join(line + end for line, end in zip(lines, ends))
    if not last_end:
        text = text[: -len(ends[len(lines) - 1])]
    path = write(tmp_path, ("\ufeff" if bom else "") + text)
    with io.CsvSource(path) as src:
        samples = [c.dataset for c in src.chunks(chunk_rows, text_columns=False)]
    got = np.concatenate([ds.readings_nT[0] for ds in samples]) if samples else np.zeros((0, 3))
    k = np.arange(1, rows + 1)
    np.testing.assert_array_equal(got, np.column_stack([k, 2 * k + 0.5, -100 * k]))  # every row, once, in order
    with io.CsvSource(path) as src:
        assert src.count_rows(block) == rows
    with open(path, "rb") as fh, io.CsvSource(fh) as src:  # an open file too (an upload)
        assert src.count_rows(block) == rows


def test_the_row_count_says_when_a_line_has_no_end():
    """A line running on past MAX_LINE_BYTES: the reader refuses the file, the count does not guess (None)."""
    data = b"s1x,s1y,s1z\n1,2,3\n" + b"4" * (io.MAX_LINE_BYTES + 10)
    with io.CsvSource(BytesIO(data)) as src:
        assert src.count_rows(1 << 16) is None


@pytest.mark.parametrize("chunk_rows", [1, 2, 5])
def test_a_run_of_blank_lines_longer_than_a_block_does_not_end_the_file(tmp_path, chunk_rows):
    """More blank lines in a row than a block's lines: the rows after them are read, with their line numbers (the
    reader stopped at the first block of blank lines, silently dropping the rest of the file)."""
    k = 3 * chunk_rows
    path = write(tmp_path, "s1x,s1y,s1z\n1,2,3\n" + "\n" * k + "  \r\n" * chunk_rows + "4,5,6\n7,8,9")
    with io.CsvSource(path) as src:
        chunks = list(src.chunks(chunk_rows))
    np.testing.assert_array_equal(
        np.concatenate([c.dataset.readings_nT[0] for c in chunks]), [[1, 2, 3], [4, 5, 6], [7, 8, 9]]
    )
    lines = np.concatenate([c.line_numbers for c in chunks])
    np.testing.assert_array_equal(lines, [2, 3 + k + chunk_rows, 4 + k + chunk_rows])
    assert read_quiet(path).n_samples == 3


@settings(max_examples=400, deadline=None)
@given(
    body=st.text(alphabet='0123456789,,,\n\n\n\r \t"#e-.\xa0\u2028\x0c', max_size=120),
    chunk_rows=st.integers(1, 5),
    block=st.integers(1, 16),
    drop_bad=st.booleans(),
)
def test_whatever_the_reader_reads_it_yields_the_counted_rows(body, chunk_rows, block, drop_bad):
    """Any text after a header: when the reader reads it without an error, it yields exactly the counted rows
    (quotes, lone carriage returns, ``#`` lines and all); with ``drop_bad`` at most that many."""
    data = ("s1x,s1y,s1z\n" + body).encode("utf-8")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DataWarning)
            with io.CsvSource(BytesIO(data)) as src:
                samples = sum(c.dataset.n_samples for c in src.chunks(chunk_rows, drop_bad=drop_bad))
    except DatasetError:
        return  # refused: the count means nothing
    with io.CsvSource(BytesIO(data)) as src:
        rows = src.count_rows(block)
    assert samples <= rows if drop_bad else samples == rows


# -- line ends: every route reads the same samples or gives the same refusal -----------------------------------------
@pytest.fixture(scope="module")
def line_end_text(tmp_path_factory):
    """A CSV written by magcal (metadata lines, time, temperature, attitude, group), its text, and its samples."""
    ds = simulate_timeseries("chi2017", n_samples=60, seed=5).sensors([0, 1])
    path = tmp_path_factory.mktemp("ends") / "lf.csv"
    io.write_csv(path, ds.replace(group=np.array(["a", "b", "c"] * 20)))
    return path.read_text(), read_quiet(path)


def _outcome(fn):
    """The dataset ``fn`` reads, or the message it refuses with."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DataWarning)
            return fn()
    except DatasetError as exc:
        return str(exc)


@pytest.mark.parametrize("variant", line_ends.VARIANTS)
def test_every_csv_route_reads_the_same_samples_or_gives_the_same_refusal(
    tmp_path, monkeypatch, line_end_text, variant
):
    """LF, CRLF, CRs piled before the LF or ending the file: read alike; CR-only (old Mac) line ends, and a CR inside
    a line, refused naming the file and the line, alike, by the whole-file reader (pyarrow: it read a row's CR as a
    line end, so ``1,2,3\\r4,5,6`` was two rows there and refused by the line reader), its line-by-line fallback,
    the block reader, ``drop_bad``; the row count is the samples of a file read."""
    text, want = line_end_text
    data, refusal = line_ends.line_end_variant(text, variant)
    path = write(tmp_path, data)

    def blocks(drop_bad):
        with io.CsvSource(path) as src:
            return io.concatenate([c.dataset for c in src.chunks(7, drop_bad=drop_bad)])

    def line_by_line():
        with monkeypatch.context() as m:
            m.setattr(io, "_read_csv_arrow", lambda *a, **k: None)
            return io.read_csv(path)

    routes = {
        "read_csv": lambda: io.read_csv(path),
        "line by line": line_by_line,
        "an open file": lambda: io.read_csv(BytesIO(data), name=str(path)),
        "blocks": lambda: blocks(False),
        "drop_bad": lambda: io.read_csv(path, drop_bad=True),
        "blocks, drop_bad": lambda: blocks(True),
    }
    got = {route: _outcome(fn) for route, fn in routes.items()}
    arrow = _outcome(lambda: io._read_csv_arrow(path, None, None, None, None))
    if refusal is None:
        assert isinstance(arrow, Dataset)  # the fast path reads it
        for route, ds in got.items():
            assert isinstance(ds, Dataset), (route, ds)
            for attr in ("readings_nT", "time_s", "temperature_C", "attitude_wxyz", "group"):
                np.testing.assert_array_equal(getattr(ds, attr), getattr(want, attr), err_msg=route)
        with io.CsvSource(path) as src:
            assert src.count_rows() == want.n_samples
        return
    messages = set(map(str, got.values()))
    assert len(messages) == 1, got
    message = messages.pop()
    assert all(isinstance(m, str) for m in got.values()), got
    assert message.startswith(f"{path}: ") and re.search(refusal, message), message
    assert arrow is None or arrow == message  # pyarrow does not read it: the line reader says why
    # the row count's source refuses a bad head alike; past the head, the count of a file refused means nothing
    assert _outcome(lambda: io.CsvSource(path).close()) in (None, message)


@settings(max_examples=300, deadline=None)
@given(
    data=st.binary(max_size=60).map(lambda b: b.translate(bytes(range(256)).replace(b"a", b"\r").replace(b"b", b"\n"))),
    start=st.integers(0, 8),
    block=st.integers(1, 9),
)
def test_a_cr_inside_a_line_is_found_wherever_the_blocks_cut(data, start, block):
    """``stray_cr`` (the whole-file reader's look for a CR inside a line) finds the first CR followed by a byte
    other than CR or LF, looked at in blocks of any size: a CR ending a block is judged by the next byte."""
    want = re.search(rb"\r[^\r\n]", data[start:])
    old, io._CR_BLOCK = io._CR_BLOCK, block
    try:
        got = io.stray_cr(data, start)
    finally:
        io._CR_BLOCK = old
    assert got == (start + want.start() if want else -1)
