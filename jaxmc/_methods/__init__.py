"""The methods `integrate` streams with, as objects (`jaxmc.methods`)."""
