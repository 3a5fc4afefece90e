"""Shared pytest configuration for magcal's tests.

The helper modules beside the tests are not test modules: importing ``user_effects_example.py`` registers its effect
for every later test (the diagnosis tests every registered effect), so neither collection nor ``--doctest-modules``
may import them.
"""

import importlib.metadata

import pytest

collect_ignore = ["user_effects_example.py", "heldout_sim.py"]


@pytest.fixture
def clean_catalogue(monkeypatch):
    """Start and end with magcal's own effect catalogue: a user's effect (from a file or an entry point) must not
    leak into other tests, since the diagnosis tests every registered effect. Installed packages' entry points are
    hidden too."""
    from magcal import plugins
    from magcal.model import EFFECTS

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
