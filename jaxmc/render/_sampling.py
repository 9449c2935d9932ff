"""Per-pixel 2-D sample patterns (from `jaxmc.points`) and the cone size of sphere lights.

The direction warps themselves are `jaxmc.warps`.
"""

from __future__ import annotations

import math

from .._points._registry import unit_points


POINT_SETS = ("uniform", "stratified", "latin_hypercube", "halton")
# The renderer's "uniform" has always drawn i.i.d. points from `jax.random`'s own stream.
_REGISTRY_NAMES = {"uniform": "jax_random_uniform"}


def grid_counts(n: int) -> tuple[int, int]:
    """The most nearly square `(a, b)` with `a * b == n` (jittered grid shape)."""
    a = math.isqrt(n)
    while n % a:
        a -= 1
    return (n // a, a)


def point_set(name: str, key, n: int):
    """`n` points on $[0,1)^2$ from the named pattern, randomised by `key`."""
    if name not in POINT_SETS:
        raise ValueError(f"`points` must be one of {POINT_SETS}, got {name!r}.")
    counts = grid_counts(n) if name == "stratified" else None
    return unit_points(_REGISTRY_NAMES.get(name, name), key, n, 2, counts=counts)
