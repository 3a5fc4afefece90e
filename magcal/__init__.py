"""magcal: calibration of triaxial fluxgate magnetometers and the four-sensor cross gradient tensor system."""

from . import conventions
from .dataset import Dataset, DatasetError
from .simulation import ArrayTruth, SensorErrors, simulate, simulate_timeseries, PRESETS

__version__ = "0.1.0"
