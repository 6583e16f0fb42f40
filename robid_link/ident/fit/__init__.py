"""The fitting room: regressor assembly, estimators, the identification pipeline and its
results, the physically consistent fit and the parameter set a controller gets."""
