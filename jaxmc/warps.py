r"""Warps: maps from the unit cube $[0,1)^k$ to other domains (PBRT 3rd ed. §13.3.1).

Every warp is the *inversion method* (PBRT 3rd ed. §13.3.1): write the target density
$p$, integrate it to its CDF $P$ (marginal then conditional, in 2-D), and
invert, $X = P^{-1}(U)$. If $U$ is uniform on $[0,1)^k$ then $X$ has density
$p$, and stratified or low-discrepancy $U$ stay well spread after the warp
because each map is monotone in its inputs.

Each warp `name(u, ...) -> x` comes with

- `name_pdf(x, ...)`: the density of `x` with respect to the *natural measure*
  of the target (length, area, or solid angle for directions), zero outside the
  support;
- `name_inverse(x, ...) -> u` where an inverse exists, so that
  `name_inverse(name(u)) == u` up to rounding.

Warps are written for one point: `u` has shape `(k,)` (a scalar for the 1-D
warps `power` and `exponential`), and any leading batch axes broadcast, so
`u` of shape `(n, k)` gives `n` points. Directions are unit 3-vectors and
hemispheres are around $+z$. Everything is differentiable where the map is
(e.g. `jax.grad` of `power(u, n)` with respect to `n`, of
`sphere_solid_angle` with respect to the light's centre and radius).

!!! Example

    ```python
    import jax, jaxmc
    u = jax.random.uniform(jax.random.key(0), (1024, 2))
    w = jaxmc.warps.hemisphere_cosine(u)          # (1024, 3), cos-weighted
    p = jaxmc.warps.hemisphere_cosine_pdf(w)      # cos(theta) / pi
    ```

References: M. Pharr, W. Jakob, G. Humphreys, *Physically Based Rendering*, 3rd ed.,
§13.3.1 (inversion; power and exponential examples), §13.6.2 (disk) and §13.6
(hemisphere, cone, triangle and sphere-light sampling); P. Shirley and K. Chiu,
"A Low Distortion Map Between Disk and Square", JGT 1997 (concentric disk);
T. Duff et al., "Building an Orthonormal Basis, Revisited", JCGT 2017.
"""

from ._warps._cone import (
    cone as cone,
    cone_inverse as cone_inverse,
    cone_pdf as cone_pdf,
    sphere_solid_angle as sphere_solid_angle,
    sphere_solid_angle_inverse as sphere_solid_angle_inverse,
    sphere_solid_angle_pdf as sphere_solid_angle_pdf,
)
from ._warps._disk import (
    disk_concentric as disk_concentric,
    disk_concentric_inverse as disk_concentric_inverse,
    disk_concentric_pdf as disk_concentric_pdf,
    disk_polar as disk_polar,
    disk_polar_inverse as disk_polar_inverse,
    disk_polar_pdf as disk_polar_pdf,
)
from ._warps._interval import (
    box as box,
    box_inverse as box_inverse,
    box_pdf as box_pdf,
    exponential as exponential,
    exponential_inverse as exponential_inverse,
    exponential_pdf as exponential_pdf,
    power as power,
    power_inverse as power_inverse,
    power_pdf as power_pdf,
)
from ._warps._sphere import (
    hemisphere_cosine as hemisphere_cosine,
    hemisphere_cosine_inverse as hemisphere_cosine_inverse,
    hemisphere_cosine_pdf as hemisphere_cosine_pdf,
    hemisphere_uniform as hemisphere_uniform,
    hemisphere_uniform_inverse as hemisphere_uniform_inverse,
    hemisphere_uniform_pdf as hemisphere_uniform_pdf,
    sphere_uniform as sphere_uniform,
    sphere_uniform_inverse as sphere_uniform_inverse,
    sphere_uniform_pdf as sphere_uniform_pdf,
)
from ._warps._triangle import (
    triangle as triangle,
    triangle_inverse as triangle_inverse,
    triangle_pdf as triangle_pdf,
)


__all__ = [
    "box",
    "box_pdf",
    "box_inverse",
    "power",
    "power_pdf",
    "power_inverse",
    "exponential",
    "exponential_pdf",
    "exponential_inverse",
    "disk_polar",
    "disk_polar_pdf",
    "disk_polar_inverse",
    "disk_concentric",
    "disk_concentric_pdf",
    "disk_concentric_inverse",
    "hemisphere_uniform",
    "hemisphere_uniform_pdf",
    "hemisphere_uniform_inverse",
    "hemisphere_cosine",
    "hemisphere_cosine_pdf",
    "hemisphere_cosine_inverse",
    "sphere_uniform",
    "sphere_uniform_pdf",
    "sphere_uniform_inverse",
    "cone",
    "cone_pdf",
    "cone_inverse",
    "triangle",
    "triangle_pdf",
    "triangle_inverse",
    "sphere_solid_angle",
    "sphere_solid_angle_pdf",
    "sphere_solid_angle_inverse",
]
