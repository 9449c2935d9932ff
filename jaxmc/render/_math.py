"""Small vector helpers that keep values *and gradients* finite.

`jnp.where` alone does not stop a NaN gradient from the untaken branch, so
every division, square root and normalisation here guards its input first.
"""

from __future__ import annotations

import jax.numpy as jnp


def dot(a, b):
    return jnp.sum(a * b, axis=-1)


def safe_sqrt(x):
    """`sqrt(max(x, 0))` with a finite gradient at and below zero."""
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


def safe_div(num, den):
    """`num / den` where `den != 0`, else 0 (gradient-safe)."""
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


def normalize(v):
    n2 = dot(v, v)[..., None]
    ok = n2 > 0
    return jnp.where(ok, v / jnp.sqrt(jnp.where(ok, n2, 1.0)), 0.0)


def frame(n):
    """An orthonormal basis `(t, b)` completing the unit vector `n` (Duff et al. 2017)."""
    sign = jnp.where(n[..., 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[..., 2])
    b = n[..., 0] * n[..., 1] * a
    t = jnp.stack([1.0 + sign * n[..., 0] ** 2 * a, sign * b, -sign * n[..., 0]], axis=-1)
    s = jnp.stack([b, sign + n[..., 1] ** 2 * a, -n[..., 1]], axis=-1)
    return t, s


def to_world(local, n):
    """Map a vector from the frame with +z = `n` to world coordinates."""
    t, s = frame(n)
    return local[..., 0:1] * t + local[..., 1:2] * s + local[..., 2:3] * n


def reflect(wo, h):
    return 2.0 * dot(wo, h)[..., None] * h - wo
