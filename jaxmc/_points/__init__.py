"""The point sets of `jaxmc.points`, one module per family, and their shared registry."""
