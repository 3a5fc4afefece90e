"""Errors magcal reports to users as one clear message (never a traceback)."""


class MagcalError(Exception):
    """Base class: a user-facing problem. The message says what is wrong and what to do."""


class CalibrationError(MagcalError):
    """The data cannot support the requested fit (non-ellipsoid, too few samples, degenerate coverage...)."""


class DataWarning(UserWarning):
    """Something in the data looks wrong but magcal can go on (dropped rows, suspicious units, poor coverage).

    Issued through :mod:`warnings`, so the CLI and the workbench can show it; filter it with
    ``warnings.simplefilter("error", magcal.errors.DataWarning)`` to make it fatal.
    """


class CoverageWarning(DataWarning):
    """The attitudes cover too little of the direction sphere for the fitted parameters to extrapolate."""


class ConvergenceWarning(UserWarning):
    """A fit stopped before converging (evaluation limit, singular equations): its parameters are not a minimum.

    :attr:`magcal.fit.FitResult.success` is False and :attr:`~magcal.fit.FitResult.message` says why.
    """
