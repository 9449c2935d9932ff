"""Directions in a cone, and towards a sphere light through the cone it subtends."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from ._common import (
    _TWO_PI,
    _check_concrete,
    _direction,
    _float,
    _frame,
    _point,
    _stack,
    _unit,
    _wrap_angle,
)


def _cone_local(u: jax.Array, one_minus_cos_max: jax.Array) -> jax.Array:
    """Cone sample in its local frame, from $1 - \\cos\\theta_{max}$ (no cancellation)."""
    q = u[..., 0] * one_minus_cos_max  # 1 - cos(theta)
    sin_theta = jnp.sqrt(jnp.maximum(q * (2.0 - q), 0.0))
    return _direction(1.0 - q, sin_theta, _TWO_PI * u[..., 1])


def _cone_pdf_value(one_minus_cos_max: jax.Array) -> jax.Array:
    return 1.0 / (_TWO_PI * one_minus_cos_max)


def cone(u: ArrayLike, cos_max: ArrayLike) -> jax.Array:
    r"""Uniform direction in the cone $\{\omega : \cos\theta \ge \cos\theta_{max}\}$ around $+z$.

    The cone's solid angle is $2\pi(1 - \cos\theta_{max})$, so
    $p(\omega) = 1/(2\pi(1 - \cos\theta_{max}))$, $p(\theta) = \sin\theta /
    (1 - \cos\theta_{max})$ on $[0, \theta_{max}]$, with CDF
    $P(\theta) = (1 - \cos\theta)/(1 - \cos\theta_{max})$. Inverting (PBRT 3rd ed.
    §13.6.4): $\cos\theta = 1 - u_1 (1 - \cos\theta_{max})$, $\phi = 2\pi u_2$.
    `cos_max = 0` is `hemisphere_uniform`, `cos_max = -1` is `sphere_uniform`.
    Differentiable in `cos_max`.

    **Arguments:**

    - `u`: shape `(..., 2)`.
    - `cos_max`: $\cos\theta_{max} \in [-1, 1)$, broadcasts over batch axes.

    **Returns:** unit vectors `(..., 3)`.
    """
    u = _point(u, 2, "u", "a point of [0,1)^2")
    cos_max = _float(cos_max)
    _check_concrete(
        lambda c: (c >= -1) & (c < 1), "`cos_max` must be in [-1, 1), got {}.", cos_max
    )
    return _cone_local(u, 1.0 - cos_max)


def cone_pdf(w: ArrayLike, cos_max: ArrayLike) -> jax.Array:
    """Solid-angle density of `cone`: $1/(2\\pi(1 - \\cos\\theta_{max}))$ inside, 0 outside."""
    w = _unit(w)
    cos_max = _float(cos_max)
    return jnp.where(w[..., 2] >= cos_max, _cone_pdf_value(1.0 - cos_max), 0.0)


def cone_inverse(w: ArrayLike, cos_max: ArrayLike) -> jax.Array:
    """Inverse of `cone`: $u = ((1 - \\cos\\theta)/(1 - \\cos\\theta_{max}), \\phi/2\\pi)$."""
    w = _unit(w)
    cos_max = _float(cos_max)
    return _stack(
        (1.0 - w[..., 2]) / (1.0 - cos_max),
        _wrap_angle(jnp.arctan2(w[..., 1], w[..., 0])),
    )


def _sphere_cone(center, radius, ref):
    """Axis and $1 - \\cos\\theta_{max}$ of the cone subtended by a sphere from `ref`.

    $\\sin^2\\theta_{max} = (r/d)^2$ and $1 - \\cos\\theta_{max} = \\sin^2\\theta_{max} /
    (1 + \\cos\\theta_{max})$, accurate for small (distant) lights. From inside the
    sphere every direction hits it: the cone is the whole sphere ($1 - \\cos = 2$).
    """
    center = _point(center, 3, "center", "the sphere's centre")
    ref = _point(ref, 3, "ref", "the reference point")
    radius = _float(radius)
    _check_concrete(lambda r: r > 0, "`radius` must be > 0, got {}.", radius)
    center, ref = jnp.broadcast_arrays(center, ref)
    d = center - ref
    dist2 = jnp.sum(d * d, axis=-1)
    inside = dist2 <= radius * radius
    safe_dist2 = jnp.where(dist2 > 0, dist2, 1.0)
    axis = d / jnp.sqrt(safe_dist2)[..., None]
    axis = jnp.where((dist2 > 0)[..., None], axis, jnp.asarray([0.0, 0.0, 1.0], d.dtype))
    sin2 = jnp.where(inside, 0.0, radius * radius / safe_dist2)
    cos_max = jnp.sqrt(jnp.maximum(1.0 - sin2, 0.0))
    one_minus_cos = jnp.where(inside, 2.0, sin2 / (1.0 + cos_max))
    return axis, one_minus_cos


def sphere_solid_angle(
    u: ArrayLike, center: ArrayLike, radius: ArrayLike, ref: ArrayLike
) -> jax.Array:
    r"""Direction from `ref` towards a sphere light, uniform in the cone it subtends.

    Seen from `ref` at distance $d$ from the centre, a sphere of radius $r$
    fills the cone around $\hat d = (c - ref)/d$ with
    $\sin\theta_{max} = r/d$. Sampling that cone uniformly (`cone`, by
    inversion, PBRT 3rd ed. §13.6.4) gives a solid-angle density
    $p(\omega) = 1/(2\pi(1 - \cos\theta_{max}))$ that is constant on the
    light, which is what the solid-angle form of the lighting integral (the
    reflection equation, PBRT 3rd ed. §5.6.1) wants; it is far better than area
    sampling ($d\omega = \cos\theta\,dA/r^2$, PBRT 3rd ed. §5.5.3) for small or
    distant spheres. Every sampled ray hits the sphere. If `ref` is inside the sphere
    the cone is the whole sphere of directions ($p = 1/4\pi$).
    $1 - \cos\theta_{max}$ is computed without cancellation, so tiny lights
    work in float32. Differentiable in `center`, `radius` and `ref`.

    **Arguments:**

    - `u`: shape `(..., 2)`.
    - `center`: the sphere's centre, shape `(..., 3)`.
    - `radius`: the sphere's radius, $> 0$.
    - `ref`: the shading point, shape `(..., 3)`.

    **Returns:** unit directions `(..., 3)` in world space.
    """
    u = _point(u, 2, "u", "a point of [0,1)^2")
    axis, one_minus_cos = _sphere_cone(center, radius, ref)
    local = _cone_local(u, one_minus_cos)
    t, b = _frame(axis)
    local, t, b, axis = jnp.broadcast_arrays(local, t, b, axis)
    return local[..., 0:1] * t + local[..., 1:2] * b + local[..., 2:3] * axis


def sphere_solid_angle_pdf(
    w: ArrayLike, center: ArrayLike, radius: ArrayLike, ref: ArrayLike
) -> jax.Array:
    r"""Solid-angle density of `sphere_solid_angle`: $1/(2\pi(1 - \cos\theta_{max}))$ for
    directions `w` inside the subtended cone (i.e. rays from `ref` that hit the
    sphere), 0 otherwise. `w` is normalised first.

    The cone test compares half-angle sines, $|w - \hat d|/2 = \sin(\theta/2)$
    against $\sin(\theta_{max}/2) = \sqrt{(1 - \cos\theta_{max})/2}$, with a
    slack of two ulps: a unit vector stored in float32 only pins its angle down
    to about $10^{-7}$ rad, which for a tiny light is a sizeable fraction of
    $\theta_{max}$, and the warp's own samples must never get a zero pdf.
    """
    w = _unit(w)
    axis, one_minus_cos = _sphere_cone(center, radius, ref)
    w = w / jnp.linalg.norm(w, axis=-1, keepdims=True)
    w, axis = jnp.broadcast_arrays(w, axis)
    diff = w - axis
    half_sin = 0.5 * jnp.sqrt(jnp.sum(diff * diff, axis=-1))
    half_sin, one_minus_cos = jnp.broadcast_arrays(half_sin, one_minus_cos)
    half_sin_max = jnp.sqrt(0.5 * one_minus_cos)
    slack = 2 * jnp.finfo(half_sin.dtype).eps
    inside = (half_sin <= half_sin_max + slack) | (one_minus_cos >= 2.0)
    return jnp.where(inside, _cone_pdf_value(one_minus_cos), 0.0)


def sphere_solid_angle_inverse(
    w: ArrayLike, center: ArrayLike, radius: ArrayLike, ref: ArrayLike
) -> jax.Array:
    """Inverse of `sphere_solid_angle` for directions inside the subtended cone."""
    w = _unit(w)
    axis, one_minus_cos = _sphere_cone(center, radius, ref)
    t, b = _frame(axis)
    w, t, b, axis = jnp.broadcast_arrays(w, t, b, axis)
    x = jnp.sum(w * t, axis=-1)
    y = jnp.sum(w * b, axis=-1)
    diff = w - axis
    one_minus_cos_w = 0.5 * jnp.sum(diff * diff, axis=-1)
    return _stack(one_minus_cos_w / one_minus_cos, _wrap_angle(jnp.arctan2(y, x)))
