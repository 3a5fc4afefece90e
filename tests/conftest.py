"""Shared pytest configuration for magcal's tests.

The tests are one package, a folder per package of magcal (``tests/README.md``); the modules in ``tests/helpers/``
are not test modules: importing ``user_effects_example.py`` registers its effect for every later test (the diagnosis
tests every registered effect), so neither collection nor ``--doctest-modules`` may import them.
"""

import importlib.metadata
import os

import pytest
from hypothesis import settings

# The suite runs in parallel processes (pytest-xdist, ``-n auto`` in pyproject.toml): one BLAS thread each, or on a
# two-core machine the workers' BLAS threads fight over the cores (the suite then takes three times as long). This
# module is loaded before the workers start, and they inherit the setting; an explicit value is kept.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

# Hypothesis draws the same examples on every run of the suite (derandomized): the suite judges the change at hand,
# not the luck of a draw. The search for new failing inputs is a campaign of its own, with fresh random examples
# each run: ``MAGCAL_HYPOTHESIS_RANDOM=1`` (benchmarks/fuzz_readers.py sets it).
settings.register_profile("suite", derandomize=True)
settings.register_profile("search", derandomize=False)
settings.load_profile("search" if os.environ.get("MAGCAL_HYPOTHESIS_RANDOM") == "1" else "suite")

#: The browser the end-to-end tests drive (Debian's chromium) and its flags.
CHROMIUM = "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--disable-background-networking"]

collect_ignore = ["helpers"]


@pytest.fixture
def clean_catalogue(monkeypatch):
    """Start and end with magcal's own effect catalogue: a user's effect (from a file or an entry point) must not
    leak into other tests, since the diagnosis tests every registered effect. Installed packages' entry points are
    hidden too."""
    from magcal.model import plugins
    from magcal.model.terms import EFFECTS

    before = dict(EFFECTS)
    monkeypatch.setattr(plugins, "_ORIGINS", {})
    monkeypatch.setattr(plugins, "_SOURCES", {})
    monkeypatch.setattr(plugins, "_USER_FILES", set())
    monkeypatch.setattr(plugins, "_ENTRY_POINTS_LOADED", False)
    monkeypatch.setattr(importlib.metadata, "entry_points", lambda **kw: [])
    for name in [n for n in EFFECTS if n not in before]:
        EFFECTS.pop(name)
    yield
    EFFECTS.clear()
    EFFECTS.update(before)


@pytest.fixture
def bench(tmp_path, request):
    """Start real workbench servers on loopback (port 0, no browser) and stop them after the test.

    ``bench(ds=None, store=True, name="data.csv", root=None, **kw)`` writes ``ds`` (default: the chi2017 time series
    of ``BENCH_SAMPLES`` samples at 2 Hz, a module may set that constant; 300 if it does not) as a CSV, opens it
    as the workbench does, with a session store in ``root`` (default ``tmp_path/sessions``) unless ``store`` is
    false, and returns the :class:`magcal_workbench.app.Workbench`; ``kw`` go to its constructor.
    """
    import magcal
    from magcal.data import io as mio
    from magcal_workbench.app import Workbench
    from magcal_workbench.session import SessionStore

    n_samples = getattr(request.module, "BENCH_SAMPLES", 300)
    made = []

    def make(ds=None, store=True, name="data.csv", root=None, **kw):
        if ds is None:
            ds = magcal.simulate_timeseries("chi2017", n_samples=n_samples, seed=5, rate_hz=2.0)
        path = tmp_path / name
        mio.write_csv(path, ds)
        wb = Workbench(
            mio.read_csv(path),
            host="127.0.0.1",
            port=0,
            store=SessionStore(root or tmp_path / "sessions") if store else None,
            content=path.read_bytes(),
            name=name,
            **kw,
        )
        made.append(wb)
        return wb

    yield make
    for wb in made:
        wb.stop()


def page_socket(port, origin=None, token=None, host="127.0.0.1", cookie=None, timeout_s=10.0):
    """An async context: the websocket a browser's page opens to a workbench on ``port`` (the ``websockets``
    package): ``token`` in the URL's query, ``cookie`` (``name=value``) in a Cookie header, ``origin`` (default the
    page's own; ``""`` for none) in the Origin header, viser's subprotocol, no size limit (the first message
    carries plotly.js)."""
    import socket

    import viser
    from websockets.asyncio.client import connect

    origin = f"http://{host}:{port}" if origin is None else origin
    query = f"/?token={token}" if token is not None else ""
    sock = socket.create_connection(("127.0.0.1", port), timeout=timeout_s)
    return connect(
        f"ws://{host}:{port}{query}",
        sock=sock,
        origin=origin or None,
        open_timeout=timeout_s,
        additional_headers={"Cookie": cookie} if cookie else None,
        subprotocols=[f"viser-v{viser.__version__}"],
        max_size=None,
    )


def ws_handshake(port, origin=None, token=None, host="127.0.0.1", cookie=None, timeout_s=10.0):
    """A local process's websocket client (the ``websockets`` package) against a workbench on ``port``: what it
    gets, ``("accepted", first message bytes)`` or ``("refused", HTTP status)``. ``token`` goes in the URL's query,
    ``cookie`` (``name=value``) in a Cookie header, ``origin`` (default the page's own) in the Origin header."""
    import asyncio

    from websockets.exceptions import InvalidStatus

    async def go():
        try:
            async with page_socket(port, origin, token, host, cookie, timeout_s) as ws:
                return "accepted", await asyncio.wait_for(ws.recv(), timeout_s)
        except InvalidStatus as exc:
            return "refused", exc.response.status_code

    return asyncio.run(asyncio.wait_for(go(), 3 * timeout_s))


@pytest.fixture
def corrupt_csv(tmp_path):
    """``corrupt_csv(path, line, column, value)``: a copy of the CSV ``path`` (``bad.csv`` in tmp_path) whose cell
    ``column`` (0-based) on line ``line`` (0-based, comment lines counted) is ``value``."""

    def corrupt(path, line, column, value):
        lines = path.read_text().splitlines()
        cells = lines[line].split(",")
        cells[column] = value
        lines[line] = ",".join(cells)
        bad = tmp_path / "bad.csv"
        bad.write_text("\n".join(lines) + "\n")
        return bad

    return corrupt


def _unavailable(reason: str):
    if os.environ.get("MAGCAL_REQUIRE_BROWSER") == "1":
        pytest.fail(f"MAGCAL_REQUIRE_BROWSER=1 but {reason}")
    pytest.skip(reason)


@pytest.fixture
def browser():
    if not os.path.exists(CHROMIUM):
        _unavailable(f"no browser at {CHROMIUM} (apt-get install chromium)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        _unavailable("the playwright package is not installed (pip install playwright)")
    with sync_playwright() as p:
        try:
            b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
        except Exception as exc:  # a browser that cannot start is the same as none
            _unavailable(f"chromium could not be started: {exc}")
        try:
            yield b
        finally:
            b.close()
