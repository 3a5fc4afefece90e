"""Errors magcal reports to users as one clear message (never a traceback)."""


class MagcalError(Exception):
    """Base class: a user-facing problem. The message says what is wrong and what to do."""


class CalibrationError(MagcalError):
    """The data cannot support the requested fit (non-ellipsoid, too few samples, degenerate coverage...)."""
