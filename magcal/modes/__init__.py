"""The fit modes: one object per way of fitting a calibration to a record
(:class:`~magcal.modes.base.FitMode`), by name in :data:`~magcal.modes.base.FIT_MODES` (:mod:`magcal.modes.base`).

``total_field`` (alias ``scalar``, :mod:`magcal.modes.total_field`) fits any record turned in a uniform field;
``vector`` (:mod:`magcal.modes.vector`) a record with the attitude and the field vector; ``gravity``
(:mod:`magcal.modes.gravity`) a magnetometer beside an accelerometer; ``compensation``
(:mod:`magcal.modes.compensation`) a scalar magnetometer beside a fluxgate on a platform (Tolles-Lawson and beyond); ``cross_compensation``
(:mod:`magcal.modes.cross_compensation`) the four-sensor cross flown through a compensation box.
:func:`~magcal.modes.base.choose_mode` picks one for a record (``"auto"``: the applicable one of highest priority)
for the command line and :func:`magcal.calibrate` alike.
"""

from magcal.modes.base import FIT_MODES, FitMode, choose_mode, fit_mode, load_entry_points, mode_choice, mode_names
from magcal.modes.compensation import COMPENSATION
from magcal.modes.cross_compensation import CROSS_COMPENSATION
from magcal.modes.gravity import GRAVITY, GravityDiagnosis
from magcal.modes.total_field import TOTAL_FIELD
from magcal.modes.vector import VECTOR

__all__ = [
    "FitMode",
    "FIT_MODES",
    "choose_mode",
    "mode_choice",
    "fit_mode",
    "mode_names",
    "load_entry_points",
    "TOTAL_FIELD",
    "VECTOR",
    "GRAVITY",
    "COMPENSATION",
    "CROSS_COMPENSATION",
    "GravityDiagnosis",
]
