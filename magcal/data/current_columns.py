"""The platform's current columns of a record: the names a user gives (``--current a,b``), the columns a current
term takes and the others it leaves, and a record's current term (the scalar's and the cross's compensation share
them).

A platform's wires each carry their own current, whose field at a sensor is that current times a fixed vector (nT
per A, one per column): a current term takes one or several columns, each its own field per ampere. The columns are
named by the user, else found by name (:data:`magcal.data.flight_columns.CURRENT_COLUMNS`): the first the term's,
the rest kept for a diagnosis to judge (each its own candidate).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from magcal.core.errors import MagcalError
from magcal.data.dataset import Dataset
from magcal.data.flight_columns import CURRENT_COLUMNS

__all__ = ["CurrentTerm", "current_columns", "current_names", "current_series"]


def current_names(current) -> tuple[str, ...]:
    """The current columns a user named: ``"cur_strb"``, ``"cur_strb,cur_com_1"`` or a sequence of names; () for
    None."""
    if current is None:
        return ()
    items = [current] if isinstance(current, str) else list(current)
    return tuple(dict.fromkeys(n.strip() for item in items for n in str(item).split(",") if n.strip()))


def _numeric(dataset: Dataset, name: str) -> bool:
    value = dataset.extra.get(name)
    return value is not None and np.asarray(value).dtype.kind in "fiu"


def current_columns(
    dataset: Dataset, current, where: str, known=CURRENT_COLUMNS
) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(the current term's columns, the record's other current columns): the named ones (``current``, one or
    several; an error naming the columns when one is absent) and none other, else the first of ``known`` the
    dataset holds as numbers and the rest of them."""
    named = current_names(current)
    if named:
        for name in named:
            if not _numeric(dataset, name):
                numeric = [k for k in dataset.extra if _numeric(dataset, k)]
                raise MagcalError(
                    f"{where}: no column {name!r} of numbers for the current (--current); its other columns: "
                    + (", ".join(numeric) or "none")
                )
        return named, ()
    found = tuple(name for name in known if _numeric(dataset, name))
    return found[:1], found[1:]


def current_series(dataset: Dataset, term, others, where: str) -> tuple[dict, dict]:
    """(the term's columns, the other columns), name -> values (A): the term's must be finite (an error naming the
    column and its first bad row), a gappy other column is no candidate and is dropped."""
    values = {c: np.asarray(dataset.extra[c], float) for c in tuple(term) + tuple(others)}
    for c in term:
        bad = ~np.isfinite(values[c])
        if bad.any():
            raise MagcalError(
                f"{where}: column {c} (a current) has {int(bad.sum())} missing or non-finite value(s) (first at "
                f"data row {int(np.argmax(bad)) + 1}): fill or cut them (or read with --drop-bad)"
            )
    return {c: values[c] for c in term}, {c: values[c] for c in others if np.isfinite(values[c]).all()}


class CurrentTerm:
    """A record's current term, for a dataclass with the term's first column's values (the field named by
    ``_CURRENT_FIELD``), its name ``current_column``, the further columns ``more_currents`` and the record's others
    ``other_currents`` (name -> values, A), and ``source``."""

    _CURRENT_FIELD = "current"
    current_column: str | None
    more_currents: dict
    other_currents: dict
    source: str

    @property
    def term_currents(self) -> dict:
        """The current term's columns, name -> values (A): the first, then the further ones."""
        first = getattr(self, self._CURRENT_FIELD)
        if first is None:
            return {}
        return {self.current_column or "current": first} | dict(self.more_currents)

    @property
    def all_currents(self) -> dict:
        """Every current column the record holds, the term's first (name -> values)."""
        term = self.term_currents
        return term | {k: v for k, v in self.other_currents.items() if k not in term}

    def taking_currents(self, columns):
        """The same record whose current term takes ``columns`` (of :attr:`all_currents`, in this order); the
        others are left to ``other_currents``."""
        every = self.all_currents
        missing = [c for c in columns if c not in every]
        if missing:
            raise MagcalError(
                f"{self.source or 'the record'}: no current column {missing[0]!r}; its currents: "
                + (", ".join(every) or "none")
            )
        names = list(dict.fromkeys(columns))
        first = names[0] if names else None
        return replace(
            self,
            **{self._CURRENT_FIELD: None if first is None else every[first]},
            current_column=first,
            more_currents={c: every[c] for c in names[1:]},
            other_currents={c: v for c, v in every.items() if c not in names},
        )
