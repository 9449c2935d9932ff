"""`Auto`: the race of candidate methods on a pilot (`jaxmc.methods.Auto`)."""
