"""magcal.core.readings_cache: computed once per readings array and key, the least recently used forgotten first."""

import numpy as np
import pytest

from magcal.core.readings_cache import ReadingsCache


def frozen(a):
    """A read-only array, as a dataset holds (magcal.data.dataset.Dataset)."""
    a = np.array(a, dtype=float)
    a.flags.writeable = False
    return a


def test_a_value_is_computed_once_per_array_and_key():
    cache, calls = ReadingsCache(4), []
    y = frozen(np.arange(12.0).reshape(4, 3))
    compute = lambda: calls.append(1) or float(y.sum())
    assert cache.get(y, ("sum",), compute) == cache.get(y, ("sum",), compute) == 66.0
    assert len(calls) == 1
    cache.get(y, ("other",), compute)  # another key
    cache.get(frozen(y), ("sum",), compute)  # another array with the same values
    assert len(calls) == 3


@pytest.mark.parametrize("size", [1, 3])
def test_the_least_recently_used_goes_first(size):
    cache, calls = ReadingsCache(size), []
    arrays = [frozen(np.full((2, 3), float(k))) for k in range(size + 1)]
    for a in arrays[:size]:
        cache.get(a, (), lambda a=a: calls.append(a[0, 0]))
    cache.get(arrays[0], (), lambda: calls.append("again"))  # used again: now the most recent
    cache.get(arrays[size], (), lambda: calls.append(size))  # evicts the least recent
    cache.get(arrays[0], (), lambda: calls.append("again"))
    assert calls.count("again") == (1 if size == 1 else 0)


def test_a_value_the_caller_refuses_is_computed_again():
    cache = ReadingsCache(2)
    y = frozen(np.zeros((3, 3)))
    assert cache.get(y, (), lambda: 1) == 1
    assert cache.get(y, (), lambda: 2, valid=lambda v: v == 2) == 2  # refused, replaced
    assert cache.get(y, (), lambda: 3, valid=lambda v: v == 2) == 2


def test_a_writable_array_is_never_kept():
    """Its values may change in place (a stale noise floor came from such an array): computed each time."""
    cache, calls = ReadingsCache(4), []
    y = np.zeros((5, 3))
    compute = lambda: calls.append(1) or float(y.sum())
    assert cache.get(y, ("sum",), compute) == 0.0
    y += 1.0
    assert cache.get(y, ("sum",), compute) == 15.0
    assert len(calls) == 2


def test_single_numbers_are_handed_to_another_holder_of_the_same_readings():
    """small_facts gives the numbers (not the arrays) kept for an array; seed keeps them for another array of the
    same readings (a worker process's view of shared memory), which then computes nothing."""
    cache, calls = ReadingsCache(8), []
    y = frozen(np.arange(12.0).reshape(4, 3))
    cache.get(y, ("index", 1), lambda: calls.append(1) or 3)
    cache.get(y, ("scan",), lambda: calls.append(1) or np.ones(4))
    cache.get(frozen(y + 1), ("index", 1), lambda: 7)  # another array's
    facts = cache.small_facts(y)
    assert facts == [(("index", 1), 3)]
    there, their_calls = ReadingsCache(8), []
    twin = frozen(y)
    for key, value in facts:
        there.seed(twin, key, value)
    assert there.get(twin, ("index", 1), lambda: their_calls.append(1) or -1) == 3 and not their_calls
    writable = np.array(y)
    there.seed(writable, ("index", 1), 3)  # never kept for an array that may change
    assert there.get(writable, ("index", 1), lambda: their_calls.append(1) or 5) == 5 and their_calls == [1]
    assert cache.small_facts(writable) == []
