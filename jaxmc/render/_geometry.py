"""Shapes and ray intersection: spheres, quads (parallelograms) and planes.

Every shape collection is an equinox Module of stacked arrays (one row per
shape) with a `Material` of the same length, so a scene is a pytree whose
numbers are all traced and differentiable. Intersection is written for one
ray and returns the distance to every shape of the collection (`inf` for a
miss); the scene takes the nearest.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ._math import dot, normalize, safe_div, safe_sqrt


T_MIN = 1e-4  # rays start this far out, past their own surface


def _rows(x, n: int, width: int | None = None):
    x = jnp.asarray(x, dtype=float)
    shape = (n,) if width is None else (n, width)
    return jnp.broadcast_to(x, shape) + jnp.zeros(shape)


class Material(eqx.Module):
    r"""Per-shape material: a diffuse base plus a Beckmann glossy lobe, and emission.

    $f = k_d/\pi + k_s\,D(h)\,G(\omega_i,\omega_o) / (4 \cos\theta_i \cos\theta_o)$,
    `roughness` the Beckmann $\alpha$; `emission` the radiance leaving the front
    side (the side the geometric normal points to; all of a sphere's surface).
    """

    diffuse: jax.Array
    specular: jax.Array
    roughness: jax.Array
    emission: jax.Array

    @classmethod
    def make(cls, n: int, *, diffuse=0.0, specular=0.0, roughness=0.1, emission=0.0):
        """`n` rows; each argument is broadcast (a scalar, an RGB triple or one row per shape)."""
        return cls(
            diffuse=_rows(diffuse, n, 3),
            specular=_rows(specular, n),
            roughness=_rows(roughness, n),
            emission=_rows(emission, n, 3),
        )

    @classmethod
    def concatenate(cls, materials):
        return cls(
            *(
                jnp.concatenate(parts)
                for parts in zip(
                    *((m.diffuse, m.specular, m.roughness, m.emission) for m in materials)
                )
            )
        )

    def __len__(self) -> int:
        return self.specular.shape[0]


class Spheres(eqx.Module):
    center: jax.Array
    radius: jax.Array
    material: Material

    def __len__(self) -> int:
        return self.radius.shape[0]

    def intersect(self, origin, direction):
        oc = origin - self.center
        b = dot(oc, direction)
        c = dot(oc, oc) - self.radius**2
        disc = b * b - c
        root = safe_sqrt(disc)
        t_near, t_far = -b - root, -b + root
        t = jnp.where(t_near > T_MIN, t_near, t_far)
        return jnp.where((disc > 0) & (t > T_MIN), t, jnp.inf)

    def normal(self, index, point):
        return normalize(point - self.center[index])


class Quads(eqx.Module):
    """Parallelograms `corner + a·edge_u + b·edge_v`, `a, b ∈ [0, 1]`; normal `edge_u × edge_v`."""

    corner: jax.Array
    edge_u: jax.Array
    edge_v: jax.Array
    material: Material

    def __len__(self) -> int:
        return self.corner.shape[0]

    @property
    def normals(self):
        return normalize(jnp.cross(self.edge_u, self.edge_v))

    @property
    def areas(self):
        return jnp.linalg.norm(jnp.cross(self.edge_u, self.edge_v), axis=-1)

    def intersect(self, origin, direction):
        n = jnp.cross(self.edge_u, self.edge_v)
        denom = dot(n, direction)
        t = safe_div(dot(n, self.corner - origin), denom)
        rel = origin + t[:, None] * direction - self.corner
        # coordinates along the edges via the dual basis: a = (rel x v)·n / |n|^2
        nn = dot(n, n)
        a = safe_div(dot(jnp.cross(rel, self.edge_v), n), nn)
        b = safe_div(dot(jnp.cross(self.edge_u, rel), n), nn)
        hit = (denom != 0) & (t > T_MIN) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)
        return jnp.where(hit, t, jnp.inf)

    def normal(self, index, point):
        del point
        return self.normals[index]


class Planes(eqx.Module):
    point: jax.Array
    normal_: jax.Array
    material: Material

    def __len__(self) -> int:
        return self.point.shape[0]

    def intersect(self, origin, direction):
        n = normalize(self.normal_)
        denom = dot(n, direction)
        t = safe_div(dot(n, self.point - origin), denom)
        return jnp.where((denom != 0) & (t > T_MIN), t, jnp.inf)

    def normal(self, index, point):
        del point
        return normalize(self.normal_[index])
