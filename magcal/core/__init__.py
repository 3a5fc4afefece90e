"""The foundations every stage stands on: the seed's conventions (defined once), errors, row-wise vector
operations, robust statistics, JSON-ready values, notes, the cache of readings-only work, and what a killed run
leaves behind. Imports nothing else of magcal."""
