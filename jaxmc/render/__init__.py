"""A small direct-lighting renderer in pure JAX that shows variance reduction as pictures.

`render(key, scene, *, strategy, spp, width, height, points="uniform")` returns a
linear RGB image; `scenes.veach_mis()` and `scenes.area_light()` are the test
scenes; `save_png` writes 8-bit sRGB.

The direction proposals the renderer samples at each shading point are public
too, for writing one's own estimators (e.g. `jaxmc.mis` at a shading point):
`CosineHemisphere`, `UniformHemisphere`, `SphereLight`, `QuadLight`,
`BeckmannLobe` and `DirectionMixture`, densities over unit directions with
respect to solid angle.
"""

from . import scenes as scenes
from ._camera import Camera as Camera
from ._directions import (
    AbstractDirections as AbstractDirections,
    BeckmannLobe as BeckmannLobe,
    CosineHemisphere as CosineHemisphere,
    DirectionMixture as DirectionMixture,
    QuadLight as QuadLight,
    SphereLight as SphereLight,
    UniformHemisphere as UniformHemisphere,
)
from ._geometry import Material as Material, Planes as Planes, Quads as Quads, Spheres as Spheres
from ._image import save_png as save_png, to_srgb8 as to_srgb8
from ._integrator import mis_parts as mis_parts, object_ids as object_ids, render as render
from ._sampling import POINT_SETS as POINT_SETS
from ._scene import STRATEGIES as STRATEGIES, Scene as Scene


__all__ = [
    "AbstractDirections",
    "BeckmannLobe",
    "Camera",
    "CosineHemisphere",
    "DirectionMixture",
    "Material",
    "POINT_SETS",
    "Planes",
    "QuadLight",
    "Quads",
    "STRATEGIES",
    "Scene",
    "SphereLight",
    "Spheres",
    "UniformHemisphere",
    "mis_parts",
    "object_ids",
    "render",
    "save_png",
    "scenes",
    "to_srgb8",
]
