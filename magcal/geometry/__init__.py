"""Closed-form estimators on arrays of readings: the sphere of directions, the ellipsoid fit (step 1 of the seed's
calibration), the orthogonal Procrustes rotation (step 2), and the shape of a sensor's readings."""
