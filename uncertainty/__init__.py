"""The world models: an ensemble of action-conditioned next-frame predictors, their training,
evaluation and disagreement scoring. Imports ``storage`` (episodes, catalog, model registry) only."""
