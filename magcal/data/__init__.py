"""Data in: the :class:`~magcal.data.dataset.Dataset`, the data CSV and Parquet files, flight-controller logs,
live sources, the simulator, and arrays or DataFrames made datasets."""
