"""magcal: calibration of triaxial fluxgate magnetometers and the four-sensor cross magnetic gradient tensor system.

The public API, in the order data flows::

    ds = magcal.read_csv("data.csv")            # or magcal.simulate("chi2017", seed=1)
    result = magcal.calibrate(ds)               # ellipsoid -> Procrustes -> maximum likelihood
    result.calibration.correct(ds)              # corrected vectors (n_sensors, N, 3), nT, array frame
    magcal.diagnose(ds, result.fit)             # ranked candidate effects with their evidence
"""

from . import conventions, effects  # effects fills the EFFECTS catalogue at import
from .calibration import Calibration, SensorCalibration
from .dataset import Dataset, DatasetError
from .diagnosis import Diagnosis, diagnose
from .errors import CalibrationError, MagcalError
from .fit import FitResult, fit
from .model import EFFECTS, Effect, Model
from .pipeline import CalibrationResult, calibrate
from .simulation import PRESETS, ArrayTruth, SensorErrors, simulate, simulate_timeseries

__version__ = "0.1.0"
