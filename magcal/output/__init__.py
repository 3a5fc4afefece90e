"""A calibration used on other data: streaming survey correction (CSV, Parquet, logs), the same on Dask, and the
parameters flight controllers load.

Importing any module of this package fills the export formats' registry (:mod:`magcal.output.export` registers
the built-in formats in :data:`magcal.output.formats.EXPORT_FORMATS` at import)."""

from magcal.output import export  # noqa: F401  (registers the built-in export formats)
