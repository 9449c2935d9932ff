"""Uniform barycentrics on the reference triangle."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from ._common import _point, _stack


def triangle(u: ArrayLike) -> jax.Array:
    r"""Uniform barycentrics $(b_0, b_1)$ on the reference triangle (pdf 2).

    The triangle $\{b_0, b_1 \ge 0,\ b_0 + b_1 \le 1\}$ has area $1/2$, so
    $p = 2$. The marginal of $b_0$ is $p(b_0) = 2(1 - b_0)$ with CDF
    $1 - (1 - b_0)^2$, and $b_1 \mid b_0$ is uniform on $[0, 1 - b_0]$.
    Inverting (with $1 - u_1 \sim u_1$): $b_0 = 1 - \sqrt{u_1}$,
    $b_1 = u_2 \sqrt{u_1}$ (PBRT-v3 `UniformSampleTriangle`). A point of a
    triangle $(p_0, p_1, p_2)$ is then $b_0 p_0 + b_1 p_1 + (1 - b_0 - b_1) p_2$,
    with area density $1/A$.

    **Arguments:** `u` of shape `(..., 2)`. **Returns:** `(..., 2)` barycentrics.
    """
    u = _point(u, 2, "u", "a point of [0,1)^2")
    s = jnp.sqrt(u[..., 0])
    return _stack(1.0 - s, u[..., 1] * s)


def triangle_pdf(b: ArrayLike) -> jax.Array:
    """Density of `triangle` w.r.t. area in the $(b_0, b_1)$ plane: 2 inside, 0 outside."""
    b = _point(b, 2, "b", "barycentrics (b0, b1)")
    b0, b1 = b[..., 0], b[..., 1]
    inside = (b0 >= 0) & (b1 >= 0) & (b0 + b1 <= 1)
    return jnp.where(inside, 2.0, 0.0).astype(b.dtype)


def triangle_inverse(b: ArrayLike) -> jax.Array:
    """Inverse of `triangle`: $u = ((1 - b_0)^2, b_1/(1 - b_0))$."""
    b = _point(b, 2, "b", "barycentrics (b0, b1)")
    s = 1.0 - b[..., 0]
    safe_s = jnp.where(s > 0, s, 1.0)
    return _stack(s * s, jnp.where(s > 0, b[..., 1] / safe_s, 0.0))
