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

from .. import warps
from ._camera import Camera
from ._geometry import T_MIN, Material, Planes, Quads, Spheres
from ._math import dot, normalize, safe_div
from ._sampling import cone_one_minus_cos_max


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

    # -- light sampling ----------------------------------------------------
    def sample_light(self, point, u):
        """Pick a light uniformly (re-using `u[0]`) and a direction towards it.

        Spheres are sampled uniformly in the cone they subtend (solid angle);
        quads uniformly by area (eq. 15), the direction being towards that point.
        Returns `(direction, g)`, `g` the light's global index.
        """
        ns, nq, _ = self._kinds()
        lights = jnp.asarray(self.lights)
        m = len(self.lights)
        scaled = u[0] * m
        i = jnp.clip(jnp.floor(scaled).astype(int), 0, m - 1)
        u = jnp.stack([jnp.clip(scaled - i, 0.0, 1.0), u[1]])
        g = lights[i]
        sphere_lights = [j for j in self.lights if j < ns]
        quad_lights = [j for j in self.lights if j >= ns]
        w = jnp.zeros(3)
        if sphere_lights:
            j = jnp.clip(g, 0, ns - 1)
            center, radius = self.spheres.center[j], self.spheres.radius[j]
            w = jnp.where(g < ns, warps.sphere_solid_angle(u, center, radius, point), w)
        if quad_lights:
            q = jnp.clip(g - ns, 0, nq - 1)
            w = jnp.where(g >= ns, normalize(self.quads.sample(q, u) - point), w)
        return w, g

    def light_pdf(self, point, direction, g, t):
        """Solid-angle density of `sample_light` at `direction`, whose ray first hits shape `g` at `t`.

        The density of the light actually hit (times the selection probability),
        0 if `g` is not a light. Uses the hit distance for quads: $p_\\omega = t^2/(A|\\cos\\theta'|)$.
        """
        ns, nq, _ = self._kinds()
        sel = 1.0 / len(self.lights)
        is_light = (
            jnp.zeros(ns + nq + len(self.planes), bool).at[jnp.asarray(self.lights)].set(True)
        )
        p = jnp.zeros(())
        if any(j < ns for j in self.lights):
            j = jnp.clip(g, 0, ns - 1)
            dist = jnp.linalg.norm(self.spheres.center[j] - point)
            omc = cone_one_minus_cos_max(self.spheres.radius[j], dist)
            p = jnp.where(g < ns, safe_div(1.0, 2.0 * jnp.pi * omc), p)
        if any(j >= ns for j in self.lights):
            q = jnp.clip(g - ns, 0, nq - 1)
            cos_l = jnp.abs(dot(self.quads.normals[q], direction))
            p = jnp.where(g >= ns, safe_div(t * t, self.quads.areas[q] * cos_l), p)
        return jnp.where((g >= 0) & is_light[jnp.maximum(g, 0)], sel * p, 0.0)


def offset(point, normal, direction):
    """Start a secondary ray just off the surface, on the side it leaves towards."""
    side = jnp.where(dot(normal, direction) >= 0, 1.0, -1.0)
    return point + (10 * T_MIN) * side * normal
