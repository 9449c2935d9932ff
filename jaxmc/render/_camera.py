"""A pinhole camera."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ._math import normalize


class Camera(eqx.Module):
    """Pinhole at `eye` looking at `target`, `up` roughly up, horizontal field of view `fov` (degrees)."""

    eye: jax.Array
    target: jax.Array
    up: jax.Array
    fov: jax.Array

    def __init__(self, eye, target, up=(0.0, 1.0, 0.0), fov=40.0):
        self.eye = jnp.asarray(eye, dtype=float)
        self.target = jnp.asarray(target, dtype=float)
        self.up = jnp.asarray(up, dtype=float)
        self.fov = jnp.asarray(fov, dtype=float)

    def ray(self, xy, width: int, height: int):
        """The ray through image position `xy = (x, y)` in pixels (origin top-left)."""
        forward = normalize(self.target - self.eye)
        right = normalize(jnp.cross(forward, self.up))
        up = jnp.cross(right, forward)
        half = jnp.tan(jnp.deg2rad(self.fov) / 2)
        sx = (2.0 * xy[0] / width - 1.0) * half
        sy = (1.0 - 2.0 * xy[1] / height) * half * (height / width)
        return self.eye, normalize(forward + sx * right + sy * up)
