"""The warps of `jaxmc.warps`, one module per target domain."""
