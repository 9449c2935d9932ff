"""Directions on the unit sphere and on the hemisphere around $+z$."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from ._common import _INV_PI, _TWO_PI, _direction, _point, _stack, _unit, _wrap_angle
from ._disk import disk_concentric, disk_concentric_inverse


def spherical_direction(cos_theta: jax.Array, phi: jax.Array) -> jax.Array:
    r"""The unit vector with polar angle $\theta$ (given by $\cos\theta \in [-1, 1]$)
    and azimuth $\phi$ around $+z$: $(\sin\theta\cos\phi, \sin\theta\sin\phi, \cos\theta)$.

    $(\cos\theta, \phi)$ are coordinates in which solid angle is plain area,
    $d\omega = d(\cos\theta)\,d\phi$; `jaxmc.testing` bins directions in them.
    """
    sin_theta = jnp.sqrt(jnp.maximum((1.0 - cos_theta) * (1.0 + cos_theta), 0.0))
    return _direction(cos_theta, sin_theta, phi)


def hemisphere_uniform(u: ArrayLike) -> jax.Array:
    r"""Uniform direction on the hemisphere around $+z$ (pdf $1/2\pi$, §2.2.3).

    With $p(\omega) = 1/2\pi$ and $d\omega = \sin\theta\,d\theta\,d\phi$,
    $p(\theta, \phi) = \sin\theta / 2\pi$: the marginal of $\theta$ is
    $\sin\theta$ with CDF $1 - \cos\theta$, and $\phi$ is uniform. Inverting
    (and using $1 - u_1 \sim u_1$) gives $\cos\theta = u_1$, $\phi = 2\pi u_2$.

    **Arguments:** `u` of shape `(..., 2)`. **Returns:** unit vectors `(..., 3)`, $z \ge 0$.
    """
    u = _point(u, 2, "u", "a point of [0,1)^2")
    return spherical_direction(u[..., 0], _TWO_PI * u[..., 1])


def hemisphere_uniform_pdf(w: ArrayLike) -> jax.Array:
    """Solid-angle density of `hemisphere_uniform`: $1/2\\pi$ for $z \\ge 0$, else 0."""
    w = _unit(w)
    return jnp.where(w[..., 2] >= 0, 1.0 / _TWO_PI, 0.0).astype(w.dtype)


def hemisphere_uniform_inverse(w: ArrayLike) -> jax.Array:
    """Inverse of `hemisphere_uniform`: $u = (\\cos\\theta, \\phi/2\\pi)$."""
    w = _unit(w)
    return _stack(w[..., 2], _wrap_angle(jnp.arctan2(w[..., 1], w[..., 0])))


def hemisphere_cosine(u: ArrayLike) -> jax.Array:
    r"""Cosine-weighted direction on the hemisphere around $+z$ (pdf $\cos\theta/\pi$).

    $p(\omega) = \cos\theta/\pi$ (normalised: $\int_{H^2}\cos\theta\,d\omega =
    \pi$) gives $p(\theta) = 2\cos\theta\sin\theta$ with CDF
    $P(\theta) = \sin^2\theta$, so $\sin\theta = \sqrt{u_1}$ and $\phi = 2\pi
    u_2$: exactly the radius of a uniform disk point (PBRT 3rd ed. §13.6.2). Hence
    Malley's method: sample the unit disk uniformly and project up,
    $z = \sqrt{1 - x^2 - y^2}$. We use `disk_concentric` for the disk, as PBRT
    does, for its low distortion.

    **Arguments:** `u` of shape `(..., 2)`. **Returns:** unit vectors `(..., 3)`, $z \ge 0$.
    """
    d = disk_concentric(u)
    z = jnp.sqrt(jnp.maximum(1.0 - jnp.sum(d * d, axis=-1), 0.0))
    return jnp.concatenate([d, z[..., None]], axis=-1)


def hemisphere_cosine_pdf(w: ArrayLike) -> jax.Array:
    """Solid-angle density of `hemisphere_cosine`: $\\max(\\cos\\theta, 0)/\\pi$."""
    w = _unit(w)
    return jnp.maximum(w[..., 2], 0.0) * _INV_PI


def hemisphere_cosine_inverse(w: ArrayLike) -> jax.Array:
    """Inverse of `hemisphere_cosine`: project to the disk, then invert the concentric map."""
    w = _unit(w)
    return disk_concentric_inverse(w[..., :2])


def sphere_uniform(u: ArrayLike) -> jax.Array:
    r"""Uniform direction on the unit sphere (pdf $1/4\pi$).

    $p(\theta) = \sin\theta / 2$ on $[0, \pi]$ has CDF $(1 - \cos\theta)/2$,
    so $\cos\theta = 1 - 2u_1$; $\phi = 2\pi u_2$ (Archimedes: $z$ is uniform on
    $[-1, 1]$).

    **Arguments:** `u` of shape `(..., 2)`. **Returns:** unit vectors `(..., 3)`.
    """
    u = _point(u, 2, "u", "a point of [0,1)^2")
    z = 1.0 - 2.0 * u[..., 0]
    # sin(theta) = sqrt(1 - z^2) = 2 sqrt(u1 (1 - u1)), without cancellation near the poles.
    sin_theta = 2.0 * jnp.sqrt(jnp.maximum(u[..., 0] * (1.0 - u[..., 0]), 0.0))
    return _direction(z, sin_theta, _TWO_PI * u[..., 1])


def sphere_uniform_pdf(w: ArrayLike) -> jax.Array:
    """Solid-angle density of `sphere_uniform`: $1/4\\pi$."""
    w = _unit(w)
    return jnp.full(w.shape[:-1], 1.0 / (4.0 * math.pi), dtype=w.dtype)


def sphere_uniform_inverse(w: ArrayLike) -> jax.Array:
    """Inverse of `sphere_uniform`: $u = ((1 - z)/2, \\phi/2\\pi)$."""
    w = _unit(w)
    return _stack((1.0 - w[..., 2]) / 2.0, _wrap_angle(jnp.arctan2(w[..., 1], w[..., 0])))
