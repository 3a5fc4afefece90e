"""A calibration used on other data: streaming survey correction (CSV, Parquet, logs), the same on Dask, and the
parameters flight controllers load."""
