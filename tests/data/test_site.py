"""magcal.data.site: a data file's ``# site:`` line read into the dataset's metadata, a malformed one said once and
left out, a site named in words kept as text."""

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from magcal.checks.reference import record_date
from magcal.core.errors import DataWarning
from magcal.data import io
from magcal.data.site import SITE_KEYS, Site, names_a_place, parse_site, record_site

HEAD = "# units: nT\n"
ROWS = "s1x,s1y,s1z\n50000,1,2\n50001,2,3\n"


def read(tmp_path, site_line, name="flight.csv"):
    path = tmp_path / name
    path.write_text(HEAD + site_line + ROWS, encoding="utf-8")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DataWarning)
        return io.read_csv(path), path


@pytest.mark.parametrize(
    "text,site",
    [
        ("53.0 N, 4.5 E, 1500 m, 2024-06-01", Site(53.0, 4.5, 1500.0, "2024-06-01")),
        ("33.9 S, 18.4 W, 0.25 km, 2019.5", Site(-33.9, -18.4, 250.0, "2019.5")),
        ("-33.9, 151.2, 12, 2024-01-31", Site(-33.9, 151.2, 12.0, "2024-01-31")),
        ("47.1° N, 8.5deg E, -20 m, 2010-03-04", Site(47.1, 8.5, -20.0, "2010-03-04")),
    ],
)
def test_a_site_line_is_read_into_the_metadata(tmp_path, text, site):
    ds, _ = read(tmp_path, f"# site: {text}\n")
    assert ds.notes == ()
    assert ds.metadata["site"] == text  # the line as written stays
    assert record_site(ds) == site
    assert float(ds.metadata["site_lat_deg"]) == site.lat_deg and ds.metadata["site_date"] == site.date
    assert record_date(ds) == site.date  # IGRF without a date takes the record's


def test_the_lesson_file_names_its_site():
    folder = Path(__file__).resolve().parents[2] / "assets" / "lessons" / "cannot-tumble"
    ds = io.read_csv(folder / "data.csv")
    truth = json.loads((folder / "lesson.json").read_text(encoding="utf-8"))["site"]  # what the line was made from
    found = record_site(ds)
    assert (found.lat_deg, found.lon_deg, found.alt_m, found.date) == (
        truth["lat_deg"],
        truth["lon_deg"],
        truth["alt_m"],
        truth["date"],
    )


@pytest.mark.parametrize(
    "text,why",
    [
        ("53.0 N, 4.5 E, 2024-06-01", "3 comma-separated part(s), not 4"),
        ("93.0 N, 4.5 E, 1500 m, 2024-06-01", "latitude '93.0 N' is outside"),
        ("53.0 E, 4.5 E, 1500 m, 2024-06-01", "latitude '53.0 E' ends in 'E'"),
        ("53.0 N, 4.5 E, 1500 ft, 2024-06-01", "altitude '1500 ft'"),
        ("53.0 N, 4.5 E, 1500 m, June 2024", "date 'June 2024'"),
        ("53.0 N, -4.5 E, 1500 m, 2024-06-01", "both a sign and E"),
    ],
)
def test_a_malformed_site_line_is_said_once_and_left_out(tmp_path, text, why):
    ds, path = read(tmp_path, f"# site: {text}\n")
    assert len(ds.notes) == 1
    said = ds.notes[0].text
    assert said.startswith(f"{path}: line 2: metadata site:") and why in said and "\n" not in said
    assert "read without the site" in said and "53.0 N, 4.5 E, 1500 m, 2024-06-01" in said  # what to write
    assert record_site(ds) is None and not any(k in ds.metadata for k in SITE_KEYS)
    np.testing.assert_array_equal(ds.readings_nT[0, 1], [50001, 2, 3])  # the data are read all the same
    with pytest.warns(DataWarning, match="metadata site"):  # the public reader says it
        io.read_csv(path)


def test_a_site_named_in_words_is_text_and_no_place(tmp_path):
    ds, _ = read(tmp_path, "# site: range B: north pad\n")
    assert ds.notes == () and ds.metadata["site"] == "range B: north pad" and record_site(ds) is None
    assert not names_a_place("range B") and names_a_place(" -3.5, 2, 0 m, 2024-01-01")


def test_a_later_site_line_replaces_the_first(tmp_path):
    ds, _ = read(tmp_path, "# site: 53.0 N, 4.5 E, 1500 m, 2024-06-01\n# site: 10 N, 20 E, 0 m, 2020-01-01\n")
    assert record_site(ds) == Site(10.0, 20.0, 0.0, "2020-01-01")
    ds, _ = read(tmp_path, "# site: 53.0 N, 4.5 E, 1500 m, 2024-06-01\n# site: 10 N, 20 E\n")
    assert record_site(ds) is None  # the last line counts, and it is malformed


def test_the_site_is_written_back_as_its_line(tmp_path):
    ds, _ = read(tmp_path, "# site: 53.0 N, 4.5 E, 1500 m, 2024-06-01\n")
    out = tmp_path / "out.csv"
    io.write_csv(out, ds)
    head = out.read_text(encoding="utf-8")
    assert "# site: 53.0 N, 4.5 E, 1500 m, 2024-06-01" in head and "site_lat_deg" not in head
    back = io.read_csv(out)
    assert record_site(back) == record_site(ds)


def test_parse_site_says_what_is_wrong():
    assert parse_site("0 N, 0 E, 0 m, 2000-01-01") == Site(0.0, 0.0, 0.0, "2000-01-01")
    with pytest.raises(ValueError, match="longitude '200 E' is outside"):
        parse_site("10 N, 200 E, 0 m, 2000-01-01")
    assert Site(-33.9, -18.4, 250.0, "2019.5").text() == "33.9 S, 18.4 W, 250 m, 2019.5"
