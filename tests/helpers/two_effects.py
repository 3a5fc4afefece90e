"""The record the parallel-diagnosis tests share: four sensors, a temperature bias and a bias step on sensor 3
hidden (both found: the forward selection runs two rounds), and its base calibration."""

from magcal.data.simulation import chi2017_truth, simulate_timeseries
from magcal.fitting.pipeline import calibrate
from magcal.model import perturbations


def two_hidden(n=3000):
    """``(dataset, calibrate(dataset))`` of ``n`` samples per sensor."""
    ds = simulate_timeseries(
        chi2017_truth(4),
        n_samples=n,
        noise_nT=3.0,
        seed=4,
        perturbations=[
            perturbations.parse_hidden("temperature_bias=2", 4),
            perturbations.parse_hidden("bias_step:3", 4),
        ],
    )
    return ds, calibrate(ds)
