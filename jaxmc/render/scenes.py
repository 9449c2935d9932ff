"""Ready-made scenes: Veach's MIS plates and a floor under an area light.

Both return a `Scene` whose numbers are traced arrays; change one with
`equinox.tree_at`, e.g. a rougher plate:

```python
scene = veach_mis()
rough = eqx.tree_at(lambda s: s.quads.material.roughness, scene,
                    scene.quads.material.roughness.at[0].set(0.01))
```
"""

from ._scenes import (
    VEACH_FLOOR_Y as VEACH_FLOOR_Y,
    VEACH_LIGHT_RADIANCE as VEACH_LIGHT_RADIANCE,
    VEACH_LIGHT_RADIUS as VEACH_LIGHT_RADIUS,
    VEACH_LIGHT_X as VEACH_LIGHT_X,
    VEACH_PLATE_DIFFUSE as VEACH_PLATE_DIFFUSE,
    VEACH_PLATE_SPECULAR as VEACH_PLATE_SPECULAR,
    VEACH_PLATES as VEACH_PLATES,
    VEACH_ROOM_ALBEDO as VEACH_ROOM_ALBEDO,
    area_light as area_light,
    veach_mis as veach_mis,
)


__all__ = [
    "VEACH_FLOOR_Y",
    "VEACH_LIGHT_RADIANCE",
    "VEACH_LIGHT_RADIUS",
    "VEACH_LIGHT_X",
    "VEACH_PLATE_DIFFUSE",
    "VEACH_PLATE_SPECULAR",
    "VEACH_PLATES",
    "VEACH_ROOM_ALBEDO",
    "area_light",
    "veach_mis",
]
