"""Shared pytest configuration for magcal's tests.

The helper modules beside the tests are not test modules: importing ``user_effects_example.py`` registers its effect
for every later test (the diagnosis tests every registered effect), so neither collection nor ``--doctest-modules``
may import them.
"""

collect_ignore = ["user_effects_example.py", "heldout_sim.py"]
