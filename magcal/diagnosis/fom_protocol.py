"""One protocol for the compensations' figures of merit, whatever their unit: the scalar's (nT, a sum of
peak-to-peak values of the band-passed scalar) and the cross's tensor (nT/m, the root sum of squares of the
components' sums).

Each FOM object keeps its unit-named fields (``fom_nT``, ``peak_to_peak_nT``; ``fom_nT_per_m``,
``maneuver_nT_per_m`` ...: public and documented) and answers the same unit-neutral accessors besides, with its
``unit``, so that a caller (the workbench's compensation sessions) reads either without knowing which:

- :class:`FOMFigures`: :class:`~magcal.diagnosis.fom.FOMTable` (``fom`` = ``fom_nT``, ``per_maneuver`` =
  ``peak_to_peak_nT``) and :class:`~magcal.diagnosis.cross_fom.TensorFOMTable` (``fom`` = ``fom_nT_per_m``,
  ``per_maneuver`` = ``maneuver_nT_per_m``).
- :class:`FOMComparison`: :class:`~magcal.diagnosis.fom.FOMReport` and
  :class:`~magcal.diagnosis.cross_fom.CrossFOMReport`.
- :class:`CandidateFOM`: ``CompensationCandidate`` (``fom_before`` = ``fom_before_nT``) and ``CrossCandidate``
  (``fom_before`` = ``fom_before_nT_per_m``, the held-out tensor FOM).
- :class:`DiagnosisFOM`: ``CompensationDiagnosis`` (``fom_held_out`` = ``fom_held_out_nT``, ``floor_fom`` =
  ``floor_fom_nT``) and ``CrossCompensationDiagnosis`` (``fom_held_out`` = ``fom_held_out_nT_per_m``,
  ``floor_fom`` = ``floor_fom_nT_per_m``).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

__all__ = ["CandidateFOM", "DiagnosisFOM", "FOMComparison", "FOMFigures"]


@runtime_checkable
class FOMFigures(Protocol):
    """A FOM table: its maneuvers, the figure per maneuver and their FOM, in :attr:`unit`."""

    unit: str
    maneuvers: list

    @property
    def fom(self) -> float:
        """The FOM over the maneuvers (:attr:`unit`)."""
        ...

    @property
    def per_maneuver(self):
        """Each maneuver's figure (:attr:`unit`), one per :attr:`maneuvers`."""
        ...


@runtime_checkable
class FOMComparison(Protocol):
    """A FOM before and after a compensation (:class:`FOMFigures` each, in :attr:`unit`) and the improvement
    ratio (dimensionless)."""

    unit: str
    before: FOMFigures
    after: FOMFigures
    improvement_ratio: float


@runtime_checkable
class CandidateFOM(Protocol):
    """A diagnosis's candidate term: its held-out FOM without and with it (:attr:`unit`; NaN when not judged)."""

    unit: str
    name: str
    judged: bool
    recommended: bool

    @property
    def label(self) -> str: ...

    @property
    def fom_before(self) -> float: ...

    @property
    def fom_after(self) -> float: ...


@runtime_checkable
class DiagnosisFOM(Protocol):
    """A compensation diagnosis: the model's held-out FOM, with the advice (None without), and what the noise alone
    leaves (:attr:`unit`)."""

    unit: str
    candidates: list
    current_columns: list

    @property
    def fom_held_out(self) -> float: ...

    @property
    def fom_final(self) -> float | None: ...

    @property
    def floor_fom(self) -> float: ...
