"""The statistical checks of `jaxmc.testing`."""
