"""What is computed from a record's readings alone, kept for the next use of the same readings.

A diagnosis looks at one record many times: every score round's candidates, the refits and the held-out fits
find their data-derived constants from the same readings, and the noise is estimated before and after each effect
is added. What depends on the readings alone (a step scan, the quadric residuals, the still stretches and the
quantization step) is computed once. A dataset's arrays are read-only (:class:`magcal.data.dataset.Dataset` copies
a writable array it is given), so a read-only array's memory location, shape and strides identify its values while
the cache holds the array (which keeps the location from being reused); a writable array is never cached.
"""

from __future__ import annotations

import collections

import numpy as np


class ReadingsCache:
    """The values computed from readings arrays, for the ``size`` most recently used (array, key) pairs.

    Parameters
    ----------
    size : int
        Entries kept; the least recently used goes first.
    """

    def __init__(self, size: int):
        self.size = int(size)
        self._entries: collections.OrderedDict = collections.OrderedDict()

    def get(self, array, key, compute, valid=None):
        """``compute()`` for ``array`` and ``key`` (a tuple), computed once while cached.

        ``valid(value)``, when given, says whether a cached value still applies (e.g. the same time stamps);
        a value it refuses is computed again and replaces it. Safe to call from several threads (at worst a
        value is computed twice).
        """
        if array.flags.writeable:  # its values may change in place: nothing about them can be kept
            return compute()
        full = _where(array) + tuple(key)
        hit = self._entries.get(full)
        if hit is not None and (valid is None or valid(hit[1])):
            try:
                self._entries.move_to_end(full)
            except KeyError:  # evicted by another thread meanwhile
                pass
            return hit[1]
        value = compute()
        self._entries[full] = (array, value)
        while len(self._entries) > self.size:
            self._entries.popitem(last=False)
        return value

    def small_facts(self, array) -> list:
        """``[(key, value)]`` of the values cached for ``array`` that are single numbers (a step's index, a
        quantization step): what another process holding the same readings can be handed (:meth:`seed`) instead of
        computing them again. Larger values (arrays) are left out."""
        if array.flags.writeable:
            return []
        where = _where(array)
        out = []
        for full, (_, value) in list(self._entries.items()):
            if full[:3] == where and isinstance(value, (int, float, np.integer, np.floating)):
                out.append((full[3:], value))
        return out

    def seed(self, array, key, value) -> None:
        """Keep ``value`` for ``array`` and ``key`` as if computed here (:meth:`small_facts` of the same readings
        held elsewhere). A writable array is never cached."""
        if array.flags.writeable:
            return
        self._entries[_where(array) + tuple(key)] = (array, value)
        while len(self._entries) > self.size:
            self._entries.popitem(last=False)

    def clear(self):
        """Forget every entry."""
        self._entries.clear()


def _where(array) -> tuple:
    """What identifies a read-only array's values while the cache holds it: its memory, shape and strides."""
    return (array.__array_interface__["data"][0], array.shape, array.strides)
