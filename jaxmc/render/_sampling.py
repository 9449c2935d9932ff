"""Per-pixel 2-D sample patterns (from `jaxmc.points`) and the cone size of sphere lights.

The direction warps themselves are `jaxmc.warps`.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from .. import points as _points
from ._math import safe_sqrt


POINT_SETS = ("uniform", "stratified", "latin_hypercube", "halton")


def grid_counts(n: int) -> tuple[int, int]:
    """The most nearly square `(a, b)` with `a * b == n` (jittered grid shape)."""
    a = math.isqrt(n)
    while n % a:
        a -= 1
    return (n // a, a)


def point_set(name: str, key, n: int):
    """`n` points on $[0,1)^2$ from the named pattern, randomised by `key`."""
    if name == "uniform":
        return jax.random.uniform(key, (n, 2))
    if name == "stratified":
        return _points.stratified(key, grid_counts(n))
    if name == "latin_hypercube":
        return _points.latin_hypercube(key, n, 2)
    if name == "halton":
        return _points.halton(n, 2, key=key)
    raise ValueError(f"`points` must be one of {POINT_SETS}, got {name!r}.")


def cone_one_minus_cos_max(radius, distance):
    r"""$1 - \cos\theta_{\max}$ of the cone a sphere subtends, without cancellation.

    With $s = r^2/d^2$: $1 - \sqrt{1 - s} = s / (1 + \sqrt{1 - s})$.
    """
    s = jnp.clip((radius / distance) ** 2, 0.0, 1.0)
    return s / (1.0 + safe_sqrt(1.0 - s))
