"""The scene: a camera and collections of spheres, quads and planes.

A `Scene` is an equinox Module: every number (positions, radii, radiance,
roughness, BRDF weights) is a traced array, so `jax.grad` of an image statistic
with respect to the scene works; only names, the list of emitters and the
strategies the scene supports are static. Shapes are numbered globally —
spheres first, then quads, then planes — and `scene.index(name)` finds one.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ._camera import Camera
from ._geometry import T_MIN, Material, Planes, Quads, Spheres
from ._math import dot


LIGHT_STRATEGIES = ("light", "brdf", "mis_balance", "mis_power", "mis_one_sample")
HEMISPHERE_STRATEGIES = ("hemisphere_uniform", "hemisphere_cosine")
STRATEGIES = LIGHT_STRATEGIES + HEMISPHERE_STRATEGIES


class Scene(eqx.Module):
    """A camera, spheres, quads and planes; emitters are listed by global index in `lights`."""

    camera: Camera
    spheres: Spheres
    quads: Quads
    planes: Planes
    names: tuple[str, ...] = eqx.field(static=True)
    lights: tuple[int, ...] = eqx.field(static=True)
    strategies: tuple[str, ...] = eqx.field(static=True, default=LIGHT_STRATEGIES)

    def __check_init__(self):
        n = len(self.spheres) + len(self.quads) + len(self.planes)
        if len(self.names) != n:
            raise ValueError(f"`names` needs one name per shape ({n}), got {len(self.names)}.")
        if not self.lights:
            raise ValueError("a scene needs at least one light in `lights`.")
        for i in self.lights:
            if not 0 <= i < len(self.spheres) + len(self.quads):
                raise ValueError(f"`lights` must index spheres or quads, got {i}.")
        unknown = set(self.strategies) - set(STRATEGIES)
        if unknown:
            raise ValueError(f"`strategies` must be among {STRATEGIES}, got {sorted(unknown)}.")

    # -- bookkeeping -------------------------------------------------------
    def index(self, name: str) -> int:
        """Global index of the shape called `name`."""
        try:
            return self.names.index(name)
        except ValueError:
            raise ValueError(f"no shape called {name!r}; shapes are {self.names}.") from None

    @property
    def material(self) -> Material:
        return Material.concatenate(
            [self.spheres.material, self.quads.material, self.planes.material]
        )

    def _kinds(self):
        ns, nq = len(self.spheres), len(self.quads)
        return ns, nq, len(self.planes)

    # -- rays --------------------------------------------------------------
    def intersect(self, origin, direction):
        """Distance to and global index of the nearest shape (`inf`, 0 on a miss)."""
        t = jnp.concatenate(
            [
                self.spheres.intersect(origin, direction),
                self.quads.intersect(origin, direction),
                self.planes.intersect(origin, direction),
            ]
        )
        g = jnp.argmin(t)
        return t[g], g

    def normal(self, g, point):
        """Geometric normal of shape `g` at `point`."""
        ns, nq, npl = self._kinds()
        out = jnp.zeros(3)
        if ns:
            out = jnp.where(g < ns, self.spheres.normal(jnp.clip(g, 0, ns - 1), point), out)
        if nq:
            q = jnp.clip(g - ns, 0, nq - 1)
            out = jnp.where((g >= ns) & (g < ns + nq), self.quads.normal(q, point), out)
        if npl:
            k = jnp.clip(g - ns - nq, 0, npl - 1)
            out = jnp.where(g >= ns + nq, self.planes.normal(k, point), out)
        return out

    def trace_emission(self, origin, direction):
        """Trace a ray; return `(radiance, g, t)`: front-side emission of the shape hit, its index and distance (0, -1, 0 on a miss)."""
        t, g = self.intersect(origin, direction)
        hit = jnp.isfinite(t)
        t_safe = jnp.where(hit, t, 0.0)
        n = self.normal(g, origin + t_safe * direction)
        front = hit & (dot(n, direction) < 0)
        le = jnp.where(front, self.material.emission[g], 0.0)
        return le, jnp.where(hit, g, -1), t_safe


def offset(point, normal, direction):
    """Start a secondary ray just off the surface, on the side it leaves towards."""
    side = jnp.where(dot(normal, direction) >= 0, 1.0, -1.0)
    return point + (10 * T_MIN) * side * normal
