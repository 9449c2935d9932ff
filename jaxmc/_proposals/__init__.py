"""The importance densities of `jaxmc.proposals`, one module per density."""
