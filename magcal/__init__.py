"""magcal: calibration of triaxial fluxgate magnetometers and the four-sensor cross magnetic gradient tensor system.

The public API, in the order data flows::

    ds = magcal.read_csv("data.csv")            # or an (N, 3) array, a DataFrame, magcal.simulate("chi2017")
    result = magcal.calibrate(ds)               # ellipsoid -> Procrustes -> maximum likelihood
    d = magcal.diagnose(ds, result)             # ranked candidate effects with their evidence, a verdict
    result = magcal.calibrate(ds, effects=d.explained_by)   # add the effect the diagnosis names
    result.calibration.correct(new_ds)          # corrected vectors (n_sensors, N, 3), nT, array frame

``calibrate`` and ``diagnose`` accept a :class:`Dataset`, an array of raw readings in nT of shape ``(N, 3)`` or
``(n_sensors, N, 3)`` (with ``t=`` in s, ``temp=`` in degC, ``reference_total_nT=``) or a pandas DataFrame with
the columns of the data CSV (docs/formats.md). :data:`EFFECTS` is the catalogue of candidate effects (complete at
import); :func:`register` adds your own :class:`Effect` subclass to it.

Examples
--------
>>> import numpy as np, magcal
>>> readings = magcal.simulate("chi2017", seed=2).readings_nT      # (4, 200, 3) raw readings, nT
>>> result = magcal.calibrate(readings, reference_total_nT=50000)
>>> result.calibration.n_sensors
4
>>> corrected = result.calibration.correct(magcal.as_dataset(readings))
>>> field = np.linalg.norm(corrected, axis=-1)                       # |B| per sensor and sample, nT
>>> bool(np.all(np.abs(field - 50000) < 20))                        # noise sigma is 3 nT per axis
True
>>> "temperature_bias" in magcal.EFFECTS
True
"""

from . import conventions, effects  # effects fills the EFFECTS catalogue at import
from .api import calibrate, diagnose, read_csv
from .calibration import Calibration, SensorCalibration
from .dataset import Dataset, DatasetError, as_dataset
from .errors import CalibrationError, MagcalError
from .fit import FitResult, fit
from .model import EFFECTS, Effect, Model, register
from .perturbations import parse_hidden
from .pipeline import CalibrationResult
from .simulation import PRESETS, ArrayTruth, SensorErrors, simulate, simulate_timeseries

__version__ = "0.1.0"

__all__ = [
    # data in
    "read_csv", "as_dataset", "Dataset", "DatasetError", "simulate", "simulate_timeseries", "parse_hidden",
    "PRESETS", "ArrayTruth", "SensorErrors",
    # calibrate, diagnose, apply
    "calibrate", "CalibrationResult", "Calibration", "SensorCalibration", "diagnose", "Diagnosis", "fit",
    "FitResult",
    # the model and its effects
    "Model", "Effect", "EFFECTS", "register",
    # flight-controller logs, live sources, parameters out
    "read_log", "open_source", "LiveSession", "export_calibration",
    # errors
    "MagcalError", "CalibrationError",
    "__version__",
]


#: Names loaded on first use (module, attribute): flight-controller logs, live sources, parameter export.
_LAZY = {"read_log": ("logs", "read_log"), "open_source": ("live", "open_source"),
         "LiveSession": ("live", "LiveSession"), "export_calibration": ("export", "export_calibration")}


def __getattr__(name):
    # the diagnosis package is loaded when first used, so ``import magcal`` stays light
    if name == "Diagnosis":
        from .diagnosis import Diagnosis

        return Diagnosis
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        return getattr(importlib.import_module(f"{__name__}.{module}"), attr)
    raise AttributeError(f"module 'magcal' has no attribute {name!r}")
