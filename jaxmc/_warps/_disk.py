"""Uniform points on the unit disk: polar inversion (PBRT 3rd ed. §13.6.2) and the concentric
map (Shirley & Chiu, "A Low Distortion Map Between Disk and Square", 1997)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from ._common import _INV_PI, _TWO_PI, _point, _stack, _wrap_angle


def _unit_disk_pdf(x: ArrayLike) -> jax.Array:
    x = _point(x, 2, "x", "a point of the plane")
    inside = jnp.sum(x * x, axis=-1) <= 1.0
    return jnp.where(inside, _INV_PI, 0.0).astype(x.dtype)


def disk_polar(u: ArrayLike) -> jax.Array:
    r"""Uniform point on the unit disk by polar inversion (PBRT 3rd ed. §13.6.2).

    The uniform density on the disk is $p(x) = 1/\pi$; in polar coordinates
    ($dA = r\,dr\,d\theta$) it is $p(r, \theta) = r/\pi$, with marginal
    $p(r) = 2r$, CDF $P(r) = r^2$, and conditional $p(\theta \mid r) =
    1/2\pi$. Inverting both gives $r = \sqrt{u_1}$, $\theta = 2\pi u_2$
    (taking $r = u_1$ instead crowds points near the centre, Fig. 4).

    **Arguments:** `u` of shape `(..., 2)`. **Returns:** `(..., 2)` points $(x, y)$.
    """
    u = _point(u, 2, "u", "a point of [0,1)^2")
    r = jnp.sqrt(u[..., 0])
    theta = _TWO_PI * u[..., 1]
    return _stack(r * jnp.cos(theta), r * jnp.sin(theta))


def disk_polar_pdf(x: ArrayLike) -> jax.Array:
    """Area density of `disk_polar`: $1/\\pi$ on the unit disk, 0 outside."""
    return _unit_disk_pdf(x)


def disk_polar_inverse(x: ArrayLike) -> jax.Array:
    """Inverse of `disk_polar`: $u = (r^2, \\theta / 2\\pi)$ with $\\theta \\in [0, 2\\pi)$."""
    x = _point(x, 2, "x", "a point of the plane")
    r2 = jnp.sum(x * x, axis=-1)
    return _stack(r2, _wrap_angle(jnp.arctan2(x[..., 1], x[..., 0])))


def disk_concentric(u: ArrayLike) -> jax.Array:
    r"""Uniform point on the unit disk by Shirley and Chiu's concentric map.

    Map $u$ to $a = 2u - 1 \in [-1, 1]^2$ and send concentric squares to
    concentric circles: in the wedge $|a_1| > |a_2|$, $r = a_1$ and
    $\theta = \frac{\pi}{4} a_2 / a_1$; otherwise $r = a_2$ and
    $\theta = \frac{\pi}{2} - \frac{\pi}{4} a_1 / a_2$. The square of
    half-width $s$ (area $4 s^2$) becomes the disk of radius $s$ (area
    $\pi s^2$) and each wedge is stretched uniformly in angle, so the area
    ratio is $\pi/4$ everywhere: the density is uniform, $1/\pi$, like
    `disk_polar`'s (PBRT 3rd ed. §13.6.2), but the map distorts areas and strata
    much less. Continuous, with a continuous inverse.

    **Arguments:** `u` of shape `(..., 2)`. **Returns:** `(..., 2)` points.
    """
    u = _point(u, 2, "u", "a point of [0,1)^2")
    a = 2.0 * u - 1.0
    a1, a2 = a[..., 0], a[..., 1]
    first = jnp.abs(a1) > jnp.abs(a2)
    safe_a1 = jnp.where(a1 == 0, 1.0, a1)
    safe_a2 = jnp.where(a2 == 0, 1.0, a2)
    r = jnp.where(first, a1, a2)
    theta = jnp.where(
        first,
        (math.pi / 4) * (a2 / safe_a1),
        (math.pi / 2) - (math.pi / 4) * (a1 / safe_a2),
    )
    return _stack(r * jnp.cos(theta), r * jnp.sin(theta))


def disk_concentric_pdf(x: ArrayLike) -> jax.Array:
    """Area density of `disk_concentric`: $1/\\pi$ on the unit disk, 0 outside."""
    return _unit_disk_pdf(x)


def disk_concentric_inverse(x: ArrayLike) -> jax.Array:
    r"""Inverse of `disk_concentric`: a point of the unit disk to $u \in [0,1]^2$.

    With $r = |x|$ and the angle $\phi$ shifted into $[-\pi/4, 7\pi/4)$, the four
    wedges are undone in turn (the forward map's $r$ is signed).
    """
    x = _point(x, 2, "x", "a point of the plane")
    r = jnp.sqrt(jnp.sum(x * x, axis=-1))
    phi = jnp.arctan2(x[..., 1], x[..., 0])
    phi = jnp.where(phi < -math.pi / 4, phi + _TWO_PI, phi)
    k = 4.0 / math.pi
    # Wedge 0: a1 = r, phi = pi/4 a2/a1.  Wedge 1: a2 = r, phi = pi/2 - pi/4 a1/a2.
    # Wedges 2, 3: the same with r -> -r and phi -> phi - pi.
    w0 = phi < math.pi / 4
    w1 = (~w0) & (phi < 3 * math.pi / 4)
    w2 = (~w0) & (~w1) & (phi < 5 * math.pi / 4)
    a1 = jnp.where(
        w0,
        r,
        jnp.where(
            w1,
            r * k * (math.pi / 2 - phi),
            jnp.where(w2, -r, -r * k * (math.pi / 2 - (phi - math.pi))),
        ),
    )
    a2 = jnp.where(
        w0,
        r * k * phi,
        jnp.where(w1, r, jnp.where(w2, -r * k * (phi - math.pi), -r)),
    )
    return _stack((a1 + 1.0) / 2.0, (a2 + 1.0) / 2.0)
