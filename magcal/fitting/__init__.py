"""From a dataset and a model to a calibration: the maximum-likelihood fitter, the seed's pipeline (ellipsoid ->
Procrustes -> maximum likelihood), global search, held-out validation and the level-table platform alignment."""
