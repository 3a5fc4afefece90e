"""One noise floor per record and mode: the figure the header, the compact table, the Quality tab, the Model tab's
verdict and the history plot all show, with where it comes from.

The total-field mode's floor is the controller's (:meth:`magcal_workbench.controller.Controller.floor_nT`: the
given noise, else the one estimated from the fit's residuals). The vector mode's is the world components' floor
the vector diagnoses found (:func:`magcal.diagnosis.vector.diagnose_vector`'s ``noise``: the white part of the
residuals, first differences in time, sensor noise along the field and the attitude's error across it). Each
diagnosis estimates it again from the residuals of the model it judges, and an effect the model leaves out only
adds to their short-term scatter, so the record's floor is the lowest estimate so far (:func:`lowest`): it does
not rise as the model changes, and it is the same figure wherever it is shown. Only reading: the estimates are the
engine's.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class Floor:
    """The open record's noise floor in the mode its loop works in.

    Attributes
    ----------
    value_nT : float or None
        The floor, nT (None while unknown).
    what : str
        Which residual it is the floor of: ``total field`` or ``world components``.
    source : str
        Where the figure comes from, in words (plain text).
    """

    value_nT: float | None
    what: str
    source: str


@dataclass(frozen=True)
class VectorNoise:
    """The vector mode's noise as held for a record (:func:`lowest`).

    Attributes
    ----------
    world_floor_nT : float
        The world components' floor, nT.
    total_noise_nT : float
        The total-field (|B|) noise behind it, RMS over the sensors, nT.
    diagnosis : int
        Which of the record's vector diagnoses found it (1 for the first).
    of : int
        How many vector diagnoses the record has had.
    given_nT : float or None
        The noise per axis the user gave (the diagnosis then used it, and the figure follows it as given).
    """

    world_floor_nT: float
    total_noise_nT: float
    diagnosis: int
    of: int
    given_nT: float | None = None

    def source(self) -> str:
        """Where the figure comes from, in words."""
        if self.given_nT is not None:
            return (
                f"the noise given, {self.given_nT:.4g} nT per axis, and the attitude error across the field the "
                f"vector diagnosis estimated; |B| noise {self.total_noise_nT:.4g} nT"
            )
        which = (
            "the vector diagnosis"
            if self.of == 1
            else f"diagnosis {self.diagnosis} of {self.of} (the lowest: a missing effect only adds to it)"
        )
        return (
            f"sensor noise along the field and attitude error across it, from the residuals' differences in time, "
            f"estimated by {which}; |B| noise {self.total_noise_nT:.4g} nT"
        )


def lowest(held: VectorNoise | None, noise, given_nT: float | None = None) -> VectorNoise | None:
    """The record's vector noise after one more diagnosis whose ``noise`` (the engine's
    :class:`magcal.diagnosis.vector.VectorNoise`: ``world_floor_nT``, ``sigma_nT`` over the sensors) is ``noise``:
    the lower of the held one and the new one (see the module's
    docstring). With a noise given (``given_nT``, nT per axis, which the diagnosis used) the new figure is taken as
    it is, and an estimate held from before the noise was given (or another given one) is dropped."""
    floor = noise.world_floor_nT
    total = noise.sigma_nT
    count = 1 if held is None else held.of + 1
    if held is not None and held.given_nT != given_nT:  # the noise was given, changed or taken back: start anew
        held, count = None, 1
    if floor is None or not np.isfinite(floor):
        return None if held is None else replace(held, of=count)
    if given_nT is None and held is not None and held.world_floor_nT <= float(floor):
        return replace(held, of=count)
    return VectorNoise(float(floor), total, count, count, given_nT)


def mode_floor(ctrl) -> Floor:
    """The open record's floor in the mode its loop works in (the vector mode where the record has attitude and a
    field vector)."""
    if ctrl.vector_loop():
        held = getattr(ctrl.vector, "noise", None)
        if held is None:
            return Floor(None, "world components", "not known yet: the vector diagnosis estimates it (Diagnose)")
        return Floor(held.world_floor_nT, "world components", held.source())
    floor = ctrl.floor_nT()
    return Floor(floor, "total field", ctrl.noise_text())


def floor_text(floor: Floor) -> str:
    """``15.13 nT`` or ``-`` (the figure only, as every place prints it)."""
    return "-" if floor.value_nT is None or not np.isfinite(floor.value_nT) else f"{floor.value_nT:.4g} nT"


def floor_markdown(ctrl) -> str:
    """The floor with what it is the floor of and its source, for the Quality tab (markdown; engine words)."""
    from .markup import safe_text

    floor = mode_floor(ctrl)
    return f"**Noise floor ({floor.what}): {floor_text(floor)}**  \n_Source: {safe_text(floor.source, 600)}_"
