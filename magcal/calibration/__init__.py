"""The calibration: fitted parameter values applied to readings (corrected vectors, the tensor), saved and loaded
as JSON, with the error bars they carry and the readable reports."""
