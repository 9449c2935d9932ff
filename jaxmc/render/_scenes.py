"""Ready-made scenes: the implementation of `jaxmc.render.scenes`."""

from __future__ import annotations

import jax.numpy as jnp

from ._camera import Camera
from ._geometry import Material, Planes, Quads, Spheres
from ._scene import LIGHT_STRATEGIES, STRATEGIES, Scene


# A reconstruction of the scene of Veach's thesis (1997), fig. 9.4 (four glossy plates lit
# by four spherical lights).
VEACH_LIGHT_X = (-3.75, -1.25, 1.25, 3.75)
VEACH_LIGHT_RADIUS = (0.03333, 0.1, 0.3, 0.9)
VEACH_LIGHT_RADIANCE = (901.803, 100.0, 11.1111, 1.23457)
VEACH_PLATES = (  # (edge A (y, z), edge B (y, z), Beckmann roughness), farthest first
    ((-2.70651, 0.25609), (-2.08375, -0.526323), 0.005),
    ((-3.28825, 1.36972), (-2.83856, 0.476536), 0.02),
    ((-3.73096, 2.70046), (-3.43378, 1.74564), 0.05),
    ((-3.99615, 4.0667), (-3.82069, 3.08221), 0.1),
)
VEACH_PLATE_DIFFUSE = (0.0175, 0.0225, 0.0325)
VEACH_PLATE_SPECULAR = 0.9675
VEACH_ROOM_ALBEDO = 0.1
VEACH_FLOOR_Y = -4.14615


def veach_mis(*, fill_light: bool = False) -> Scene:
    """Four glossy plates (roughness 0.005 → 0.1 towards the camera) under four
    spherical lights of equal power (radius 1/30 → 0.9), in a dim room.

    Shapes: `light1`–`light4` (left to right; `fill` too with `fill_light=True`, a
    unit sphere at (0, 4, 3) of radiance 100), `plate1` (farthest, smoothest) to
    `plate4` (nearest, roughest), `floor`, `wall`.
    """
    centers = [(x, 0.0, 0.0) for x in VEACH_LIGHT_X]
    radii = list(VEACH_LIGHT_RADIUS)
    radiance = list(VEACH_LIGHT_RADIANCE)
    names = ["light1", "light2", "light3", "light4"]
    if fill_light:
        centers.append((0.0, 4.0, 3.0))
        radii.append(1.0)
        radiance.append(100.0)
        names.append("fill")
    ns = len(radii)
    spheres = Spheres(
        center=jnp.asarray(centers, dtype=float),
        radius=jnp.asarray(radii, dtype=float),
        material=Material.make(ns, emission=jnp.asarray(radiance, dtype=float)[:, None]),
    )
    corners, edges_v = [], []
    for (ya, za), (yb, zb), _ in VEACH_PLATES:
        corners.append((-4.0, ya, za))
        edges_v.append((0.0, yb - ya, zb - za))
    corners += [(-10.0, VEACH_FLOOR_Y, -10.0), (-10.0, -10.0, -2.0)]
    edges_u = [(8.0, 0.0, 0.0)] * 4 + [(0.0, 0.0, 30.0), (20.0, 0.0, 0.0)]
    edges_v += [(20.0, 0.0, 0.0), (0.0, 20.0, 0.0)]
    plates = Material.make(
        4,
        diffuse=VEACH_PLATE_DIFFUSE,
        specular=VEACH_PLATE_SPECULAR,
        roughness=jnp.asarray([r for *_, r in VEACH_PLATES], dtype=float),
    )
    room = Material.make(2, diffuse=VEACH_ROOM_ALBEDO, roughness=1.0)
    quads = Quads(
        corner=jnp.asarray(corners, dtype=float),
        edge_u=jnp.asarray(edges_u, dtype=float),
        edge_v=jnp.asarray(edges_v, dtype=float),
        material=Material.concatenate([plates, room]),
    )
    planes = Planes(jnp.zeros((0, 3)), jnp.zeros((0, 3)), Material.make(0))
    return Scene(
        camera=Camera(eye=(0.0, 6.0, 27.5), target=(0.0, -1.5, 2.5), fov=25.0),
        spheres=spheres,
        quads=quads,
        planes=planes,
        names=tuple(names + ["plate1", "plate2", "plate3", "plate4", "floor", "wall"]),
        lights=tuple(range(ns)),
        strategies=LIGHT_STRATEGIES,
    )


def area_light(*, radiance: float = 6.0, size: float = 1.5, height: float = 1.5) -> Scene:
    """A diffuse floor (the plane y = 0, albedo 0.5) and a diffuse ball under one
    square light facing down — the setting of dω = cos θ dA / r² (PBRT 3rd ed. §5.5.3),
    where sampling the hemisphere (uniformly or by cosine) competes with sampling
    the light's area.

    Shapes: `ball`, `light`, `floor`.
    """
    half = size / 2
    spheres = Spheres(
        center=jnp.asarray([[0.7, 0.35, 0.4]]),
        radius=jnp.asarray([0.35]),
        material=Material.make(1, diffuse=(0.6, 0.45, 0.3)),
    )
    quads = Quads(  # edge_u x edge_v points down (-y): the emitting side
        corner=jnp.asarray([[-half, height, -half]]),
        edge_u=jnp.asarray([[size, 0.0, 0.0]]),
        edge_v=jnp.asarray([[0.0, 0.0, size]]),
        material=Material.make(1, emission=radiance),
    )
    planes = Planes(
        point=jnp.zeros((1, 3)),
        normal_=jnp.asarray([[0.0, 1.0, 0.0]]),
        material=Material.make(1, diffuse=0.5),
    )
    return Scene(
        camera=Camera(eye=(0.0, 1.1, 5.0), target=(0.0, 0.5, 0.0), fov=45.0),
        spheres=spheres,
        quads=quads,
        planes=planes,
        names=("ball", "light", "floor"),
        lights=(1,),
        strategies=STRATEGIES,
    )
