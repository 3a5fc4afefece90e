"""The foundations every stage stands on: the seed's conventions (defined once), errors, row-wise vector
operations, robust statistics, JSON-ready values, notes, and the cache of readings-only work. Imports nothing else
of magcal."""
