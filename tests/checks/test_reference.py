"""magcal.checks.reference: where the reference total field comes from, said in words."""

import argparse
import datetime as dt
import re

import numpy as np
import pytest

from magcal.checks import reference as ref
from magcal.core.errors import DataWarning, MagcalError
from magcal.data.simulation import simulate


@pytest.fixture
def ds():
    return simulate("chi2017", n_samples=50, seed=1)  # reference_total_nT metadata 50 000


def test_a_given_number_wins_and_is_said(ds):
    r = ref.resolve_reference(ds.replace(ref_total_nT=np.full(50, 50_001.0)), "50010")
    value, text = r
    assert value == 50_010.0 and r.kind == "number"
    assert "50010.0 nT" in text and "not used" in text


def test_column_then_metadata_then_fitted(ds):
    col = 50_000 + np.linspace(-3, 3, 50)
    r = ref.resolve_reference(ds.replace(ref_total_nT=col))
    assert r.kind == "column" and np.array_equal(r.value_nT, col) and "ref_total column" in r.text
    r = ref.resolve_reference(ds)
    assert r.kind == "metadata" and r.value_nT == 50_000.0
    r = ref.resolve_reference(ds.replace(reference_total_nT=None))
    assert r.kind == "fitted" and r.value_nT is None and "fitted" in r.text and not r.known


@pytest.mark.parametrize("choice", ["fit", "none", "FIT"])
def test_fit_on_request(ds, choice):
    r = ref.resolve_reference(ds, choice)
    assert r.value_nT is None and "fitted" in r.text


def test_column_on_request_needs_the_column(ds):
    with pytest.raises(MagcalError, match="no ref_total column"):
        ref.resolve_reference(ds, "column")


def test_apply_stores_scalar_or_array(ds):
    assert ref.Reference(52_000.0, "", "number").apply(ds).reference_total_nT == 52_000.0
    out = ref.Reference(np.full(50, 51_000.0), "", "column").apply(ds)
    assert np.all(out.ref_total_nT == 51_000.0)
    assert ref.Reference(None, "", "fitted").apply(ds).reference_total_nT is None


@pytest.mark.parametrize(
    "value,match",
    [
        ("52.193", "looks like uT"),
        ("0.52193", "looks like G"),
        ("521.93", "looks like mG"),
        ("-50000", "positive"),
        ("nan", "finite"),
        ("lots", "neither a number"),
    ],
)
def test_bad_numbers_are_refused(value, match):
    with pytest.raises(MagcalError, match=match):
        ref.resolve_reference(None, value)


def _said(reference, pattern) -> bool:
    """Whether the reference's checks noted ``pattern`` (a DataWarning note: said, never raised, by the step)."""
    return any(n.is_a(DataWarning) and re.search(pattern, n.text) for n in reference.notes)


def test_out_of_range_without_a_unit_explanation_warns():
    r = ref.resolve_reference(None, "150000")
    assert _said(r, "coil") and r.value_nT == 150_000.0


def test_reference_far_from_the_readings_warns(ds):
    assert _said(ref.resolve_reference(ds, "35000"), "differs from the reference")


def test_a_hard_iron_offset_is_not_a_reference_mismatch(ds):
    """The comparison uses the field the readings imply (about their centre), not the raw magnitude."""
    shifted = ds.replace(readings_nT=ds.readings_nT + np.array([70_000.0, -40_000.0, 20_000.0]))
    assert ref.resolve_reference(shifted, "50000").notes == []
    assert _said(ref.resolve_reference(shifted, "20000"), "differs from the reference")


def test_igrf_is_consistent_and_physical():
    total, comps = ref.igrf_total_nT(36.07, 120.38, 0.0, "2019-06-01")  # Qingdao, the patent's home
    assert total == pytest.approx(np.sqrt(comps["north_nT"] ** 2 + comps["east_nT"] ** 2 + comps["down_nT"] ** 2))
    assert 45_000 < total < 58_000 and 45 < comps["inclination_deg"] < 60  # mid-latitude northern hemisphere
    polar, _ = ref.igrf_total_nT(-80.0, 120.0, 0.0, "2019-06-01")
    equator, eq = ref.igrf_total_nT(0.0, -40.0, 0.0, "2019-06-01")  # the South Atlantic Anomaly region
    assert polar > 55_000 > 30_000 > equator
    assert abs(eq["inclination_deg"]) < 45
    # altitude: the dipole part falls as r^-3, (6371/7371)^3 ~ 0.65 at 1000 km; higher degrees fall faster
    high, _ = ref.igrf_total_nT(36.07, 120.38, 1000.0, "2019-06-01")
    assert 0.55 < high / total < (6371 / 7371) ** 3


def test_igrf_reference_text_names_place_date_and_limits():
    r = ref.resolve_reference(None, "igrf", lat=36.07, lon=120.38, alt_km=0.1, date="2019-06-01")
    assert r.kind == "igrf" and 45_000 < r.value_nT < 58_000
    for needle in ("IGRF", "36.0700 N", "120.3800 E", "2019-06-01", "anomalies"):
        assert needle in r.text


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({}, "needs the place"),
        ({"lat": 95, "lon": 0}, "--lat"),
        ({"lat": 10, "lon": "east"}, "--lon"),
        ({"lat": 10, "lon": 0, "date": "1850-01-01"}, "outside the IGRF"),
        ({"lat": 10, "lon": 0, "date": "next tuesday"}, "not a date"),
    ],
)
def test_igrf_bad_arguments(kwargs, match):
    with pytest.raises(MagcalError, match=match):
        ref.resolve_reference(None, "igrf", **kwargs)


@pytest.mark.parametrize(
    "text,expected",
    [
        ("2024-06-01", dt.datetime(2024, 6, 1)),
        ("2024.5", dt.datetime(2024, 7, 2)),
        (dt.date(2020, 1, 2), dt.datetime(2020, 1, 2)),
    ],
)
def test_parse_date(text, expected):
    got = ref.parse_date(text)
    assert abs((got - expected).total_seconds()) < 86_400


def test_cli_arguments_round_trip(ds):
    parser = argparse.ArgumentParser()
    ref.add_reference_arguments(parser)
    args = parser.parse_args(["--reference", "igrf", "--lat", "36", "--lon", "120", "--date", "2020-01-01"])
    assert ref.reference_from_args(args).kind == "igrf"
    assert ref.reference_from_args(parser.parse_args([]), ds).kind == "metadata"


def test_reference_check_goes_through_the_fitted_shape():
    """With a hard iron 6x the field and gains differing 2.2x (QMC5883L) the field the readings imply is
    the fitted one; the raw magnitude (or a sphere about the origin) read '+166 % above IGRF'."""
    from scipy.spatial.transform import Rotation

    from magcal.data.dataset import Dataset

    rng = np.random.default_rng(3)
    b = Rotation.random(2000, random_state=rng).apply([0.0, 0.0, 23_000.0])
    y = b @ np.diag([1.0, 0.67, 1.48]).T + 6 * 23_000.0 * np.array([0.85, 0.03, 0.52]) + rng.normal(0, 300, b.shape)
    ds = Dataset(readings_nT=y[None], source="qmc-like.csv")
    assert ref.resolve_reference(ds, "23000").notes == []
    assert _said(ref.resolve_reference(ds, "46000"), r"differs from the reference 46000 nT by -50%")


SITE = {"site": "53.0 N, 4.5 E, 1500 m, 2024-06-01", "site_lat_deg": "53.0", "site_lon_deg": "4.5"}
SITE |= {"site_alt_m": "1500.0", "site_date": "2024-06-01"}


def test_igrf_place_takes_the_site_and_given_values_win(ds):
    """:func:`igrf_place`: the file's ``# site:`` line where no place is given; given values win, each alone."""
    sited = ds.replace(metadata={**ds.metadata, **SITE})
    place = ref.igrf_place(sited)
    assert place.from_site and (place.lat_deg, place.lon_deg, place.alt_m, place.date) == (
        53.0,
        4.5,
        1500.0,
        "2024-06-01",
    )
    assert place.alt_km == 1.5
    assert place.words() == "IGRF at the file's # site: line (53 N, 4.5 E, 1500 m, 2024-06-01)"
    given = ref.igrf_place(sited, lat=-30.0, lon=20.0)
    assert not given.from_site and (given.lat_deg, given.lon_deg, given.alt_km, given.date) == (
        -30,
        20,
        0,
        "2024-06-01",
    )
    higher = ref.igrf_place(sited, alt_km=3.0, date="2025-01-01")
    assert (higher.lat_deg, higher.alt_m, higher.date) == (53.0, 3000.0, "2025-01-01") and "given" in higher.words()
    assert ref.igrf_place(ds) is None
    with pytest.raises(MagcalError, match="--lat is given without --lon"):
        ref.igrf_place(sited, lat=10.0)


def test_igrf_at_the_site_equals_igrf_at_the_typed_place(ds):
    sited = ds.replace(metadata={**ds.metadata, **SITE})
    by_site = ref.resolve_reference(sited, "igrf")
    typed = ref.resolve_reference(ds, "igrf", lat=53.0, lon=4.5, alt_km=1.5, date="2024-06-01")
    assert by_site.value_nT == typed.value_nT
    assert by_site.text.startswith("IGRF at the file's # site: line (53 N, 4.5 E, 1500 m, 2024-06-01)")
    vec = ref.resolve_vector_reference(sited, "igrf")
    vec_typed = ref.resolve_vector_reference(ds, "igrf", lat=53.0, lon=4.5, alt_km=1.5, date="2024-06-01")
    assert vec.kind == "igrf" and np.array_equal(vec.ned_nT, vec_typed.ned_nT)
    assert "# site: line" in vec.text and "# site: line" not in vec_typed.text
    over = ref.resolve_reference(sited, "igrf", lat=-30.0, lon=20.0)
    assert over.value_nT != typed.value_nT and "is not used" in over.text


def test_a_track_beats_the_site_for_the_vector_reference(ds):
    """A record with ``lat, lon`` columns and a ``# site:`` line: IGRF along the track (where each sample was
    taken), not at the site; typed values still win over both."""
    n = ds.n_samples
    track = {"lat": np.linspace(-20.0, -19.0, n), "lon": np.full(n, 140.0), "alt_m": np.full(n, 300.0)}
    tracked = ds.replace(metadata={**ds.metadata, **SITE}, extra={**ds.extra, **track})
    along = ref.resolve_vector_reference(tracked, "igrf", date="2024-06-01")
    plain = ref.resolve_vector_reference(ds.replace(extra={**ds.extra, **track}), "igrf", date="2024-06-01")
    at_site = ref.resolve_vector_reference(ds.replace(metadata={**ds.metadata, **SITE}), "igrf")
    np.testing.assert_array_equal(along.ned_nT, plain.ned_nT)
    assert not np.allclose(along.ned_nT[0], at_site.ned_nT[0], atol=1000.0)  # 53 N against 20 S: another field
    typed = ref.resolve_vector_reference(tracked, "igrf", lat=53.0, lon=4.5, alt_km=1.5, date="2024-06-01")
    np.testing.assert_array_equal(typed.ned_nT, at_site.ned_nT)
