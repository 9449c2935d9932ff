"""Argument checks and small vector helpers shared by the warps."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from .._checks import is_concrete


_TWO_PI = 2.0 * math.pi
_INV_PI = 1.0 / math.pi


def _float(x: ArrayLike) -> jax.Array:
    """`x` as a floating array (integers become the default float dtype)."""
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


def _point(x: ArrayLike, k: int, name: str, what: str) -> jax.Array:
    """A floating array whose last axis has length `k` (one point of `what`)."""
    x = _float(x)
    if x.ndim == 0 or x.shape[-1] != k:
        raise ValueError(
            f"`{name}` must have shape (..., {k}) ({what}), got shape {x.shape}. "
            "Warps are written for one point; leading axes are batch axes."
        )
    return x


def _unit(w: ArrayLike, name: str = "w") -> jax.Array:
    return _point(w, 3, name, "a direction, a unit 3-vector")


def _check_concrete(ok, message: str, *values) -> None:
    """Raise `ValueError(message)` if all `values` are concrete and `ok(*values)` fails."""
    if all(is_concrete(v) for v in values):
        arrays = [np.asarray(v) for v in values]
        if not np.all(ok(*arrays)):
            raise ValueError(message.format(*arrays))


def _stack(*components: jax.Array) -> jax.Array:
    components = jnp.broadcast_arrays(*components)
    return jnp.stack(components, axis=-1)


def _wrap_angle(phi: jax.Array) -> jax.Array:
    """An angle from `atan2` (in $(-\\pi, \\pi]$) as a fraction of a turn in $[0, 1)$."""
    t = phi / _TWO_PI
    t = jnp.where(t < 0, t + 1.0, t)
    return jnp.where(t >= 1.0, t - 1.0, t)


def _direction(cos_theta, sin_theta, phi) -> jax.Array:
    return _stack(sin_theta * jnp.cos(phi), sin_theta * jnp.sin(phi), cos_theta)


def _frame(n: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Tangents `(t, b)` completing the unit vector `n` to a right-handed frame.

    Branch-free construction of Duff et al. (JCGT 2017); stable for all `n`,
    including $n = \\pm z$.
    """
    x, y, z = n[..., 0], n[..., 1], n[..., 2]
    sign = jnp.where(z >= 0, 1.0, -1.0).astype(n.dtype)
    a = -1.0 / (sign + z)
    b = x * y * a
    t = _stack(1.0 + sign * x * x * a, sign * b, -sign * x)
    s = _stack(b, sign + y * y * a, -y)
    return t, s
