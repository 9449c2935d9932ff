"""The estimator family; public names are re-exported by `jaxmc.estimators`."""
