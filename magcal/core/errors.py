"""Errors magcal reports to users as one clear message (never a traceback)."""


class MagcalError(Exception):
    """Base class: a user-facing problem. The message says what is wrong and what to do."""


class CalibrationError(MagcalError):
    """The data cannot support the requested fit (non-ellipsoid, too few samples, degenerate coverage...)."""


class DataWarning(UserWarning):
    """Something in the data looks wrong but magcal can go on (dropped rows, suspicious units, poor coverage).

    Issued through :mod:`warnings`, so the CLI and the workbench can show it; filter it with
    ``warnings.simplefilter("error", magcal.core.errors.DataWarning)`` to make it fatal.
    """


class CoverageWarning(DataWarning):
    """The attitudes cover too little of the direction sphere for the fitted parameters to extrapolate."""


class ConvergenceWarning(UserWarning):
    """A fit stopped before converging (evaluation limit, singular equations): its parameters are not a minimum.

    :attr:`magcal.fitting.fitter.FitResult.success` is False and :attr:`~magcal.fitting.fitter.FitResult.message` says why.
    """


class RecordTermWarning(UserWarning):
    """A calibration's record-only terms were dropped (or applied without proof) on data that may not be the
    record they were fitted on.

    Terms such as ``bias_drift``, ``bias_step``, ``reference_drift`` and ``site_gradient``
    (:attr:`magcal.model.terms.Effect.transferable` False) describe one recording, not the instrument; on another record
    they would add that recording's drift or step to the new data. :meth:`magcal.calibration.calibration.Calibration.correct`
    drops them there by default; ``record_terms="apply"`` keeps them.
    """


def exception_text(exc: BaseException, limit: int = 200) -> str:
    """``Type: message`` of an exception raised by a library on a damaged input, for a one-line user message:
    whitespace runs (line ends included) become one space, other control characters are shown escaped, and the
    text is cut at ``limit`` characters."""
    text = " ".join(str(exc).split())
    if not text.isprintable():
        text = "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)
    if len(text) > limit:
        text = text[:limit] + "..."
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__
