"""magcal: calibration of triaxial fluxgate magnetometers and the four-sensor cross magnetic gradient tensor system.

The public API, in the order data flows::

    ds = magcal.read_csv("data.csv")            # or an (N, 3) array, a DataFrame, magcal.simulate("chi2017")
    result = magcal.calibrate(ds)               # the fit the record holds what it needs for (magcal.choose_mode):
                                                # ellipsoid -> Procrustes -> maximum likelihood on readings alone
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

import importlib

# Only numpy and scipy.linalg load with ``import magcal``: each public name loads its module when first used
# (``import magcal`` is paid by every command line call and every process of a parallel apply).
import numpy  # noqa: F401
import scipy.linalg  # noqa: F401

__version__ = "0.1.0"

#: Each public name and the module that holds it, in the order data flows.
_PUBLIC = {
    # data in
    "read_csv": "magcal.data.io",
    "as_dataset": "magcal.data.inputs",
    "Dataset": "magcal.data.dataset",
    "DatasetError": "magcal.data.dataset",
    "simulate": "magcal.data.simulation",
    "simulate_timeseries": "magcal.data.simulation",
    "PRESETS": "magcal.data.simulation",
    "ArrayTruth": "magcal.data.simulation",
    "SensorErrors": "magcal.data.simulation",
    "parse_hidden": "magcal.model.perturbations",
    # calibrate, diagnose, apply
    "calibrate": "magcal.api",
    "diagnose": "magcal.api",
    "ModeResult": "magcal.fitting.result",
    "FitMode": "magcal.modes",
    "FIT_MODES": "magcal.modes",
    "choose_mode": "magcal.modes",
    "CalibrationResult": "magcal.fitting.pipeline",
    "Calibration": "magcal.calibration.calibration",
    "SensorCalibration": "magcal.calibration.calibration",
    "Diagnosis": "magcal.diagnosis",
    "fit_vector": "magcal.fitting.vector",
    "VectorFitResult": "magcal.fitting.vector",
    "resolve_vector_reference": "magcal.checks.reference",
    "simulate_vehicle": "magcal.data.vehicle",
    "fit": "magcal.fitting.fitter",
    "FitResult": "magcal.fitting.fitter",
    # the model and its effects
    "Model": "magcal.model.terms",
    "Effect": "magcal.model.terms",
    "EFFECTS": "magcal.model",
    "register": "magcal.model.terms",
    # flight-controller logs, live sources, parameters out
    "read_log": "magcal.data.logs",
    "open_source": "magcal.data.live",
    "LiveSession": "magcal.data.live",
    "export_calibration": "magcal.output.export",
    # errors
    "MagcalError": "magcal.core.errors",
    "CalibrationError": "magcal.core.errors",
}

__all__ = [*_PUBLIC, "__version__"]


def __getattr__(name):
    if name in _PUBLIC:
        value = getattr(importlib.import_module(_PUBLIC[name]), name)
        globals()[name] = value  # found at once the next time
        return value
    raise AttributeError(f"module 'magcal' has no attribute {name!r}")


def __dir__():
    return sorted([*globals(), *_PUBLIC])
