r"""Direct lighting: one bounce from the camera to the lights, by several strategies.

For a camera ray hitting a point $x$ with normal $n$, the pixel collects the
emission seen directly plus the reflected direct light

$$ L(x, \omega_o) = \int_{H^2} f(\omega_o, \omega_i)\, L_e(x, \omega_i) \cos\theta_i \, d\omega_i , $$

estimated with one of the strategies below. Each builds the direction
proposals of `jaxmc.render` at the shading point (`SphereLight`, `QuadLight`,
`DirectionMixture` of `BeckmannLobe` and `CosineHemisphere`, `UniformHemisphere`)
and draws from their `warp`, so the pixel's 2-D point pattern drives them.

- `"light"`: choose a light uniformly, sample the cone a sphere subtends
  (solid angle) or a point on a quad by area ($d\omega = \cos\theta\,dA/r^2$,
  PBRT 3rd ed. §5.5.3), shadow ray against all geometry: $f L_e \cos\theta_i / p_L$;
- `"brdf"`: sample the BRDF (glossy lobe or cosine), trace, and collect the
  emission hit: $f L_e \cos\theta_i / p_B$;
- `"mis_balance"`, `"mis_power"`: one light and one BRDF sample per spp,
  weighted by the balance heuristic $w_k = p_k / \sum_l p_l$ or the power
  heuristic $w_k = p_k^2 / \sum_l p_l^2$ (Veach's multi-sample model);
- `"mis_one_sample"`: each draw picks light or BRDF sampling with probability
  $c_L = c_B = 1/2$ and scores $f L_e\cos\theta_i / (c_L p_L + c_B p_B)$ (the
  one-sample model with the balance heuristic); two draws per spp, so it
  costs the same as the multi-sample MIS strategies;
- `"hemisphere_uniform"`, `"hemisphere_cosine"` (scenes that list them):
  directions uniform on the hemisphere ($p = 1/2\pi$) or cosine-weighted
  ($p = \cos\theta/\pi$) around the normal.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from .._checks import check_count, check_key
from .._estimators._mis_weights import mis_weights
from . import _brdf
from ._directions import (
    BeckmannLobe,
    CosineHemisphere,
    DirectionMixture,
    QuadLight,
    SphereLight,
    UniformHemisphere,
)
from ._math import dot, safe_div
from ._sampling import POINT_SETS, point_set
from ._scene import STRATEGIES, Scene, offset


ONE_SAMPLE_LIGHT_PROBABILITY = 0.5
_PARTS = "/parts"  # suffix of the private strategies that keep MIS's two terms apart


def _distance(point, origin, direction, t):
    """Distance from the shading `point` to the hit `origin + t direction` (rays start offset)."""
    return jnp.linalg.norm(origin + t * direction - point)


def _pick_light(scene: Scene, u):
    """Choose one of the scene's lights uniformly with `u[0]` (rescaled for re-use): `(g, u)`."""
    m = len(scene.lights)
    scaled = u[0] * m
    i = jnp.clip(jnp.floor(scaled).astype(int), 0, m - 1)
    return jnp.asarray(scene.lights)[i], jnp.stack([jnp.clip(scaled - i, 0.0, 1.0), u[1]])


def _light_proposals(scene: Scene, point, g):
    """The direction proposals of light `g` (a traced global index) seen from `point`:
    `(sphere, quad)`, `None` for a kind of shape the scene's lights do not include."""
    ns = len(scene.spheres)
    sphere = quad = None
    if any(j < ns for j in scene.lights):
        j = jnp.clip(g, 0, ns - 1)
        sphere = SphereLight(scene.spheres.center[j], scene.spheres.radius[j], point)
    if any(j >= ns for j in scene.lights):
        q = jnp.clip(g - ns, 0, len(scene.quads) - 1)
        quads = scene.quads
        quad = QuadLight(quads.corner[q], quads.edge_u[q], quads.edge_v[q], point)
    return sphere, quad


class _Shading:
    """Everything known at the point a camera ray hit, and its direction proposals."""

    def __init__(self, scene: Scene, origin, direction):
        t, g = scene.intersect(origin, direction)
        self.hit = jnp.isfinite(t)
        t = jnp.where(self.hit, t, 0.0)
        point = origin + t * direction
        n = scene.normal(g, point)
        mat = scene.material
        self.emitted = jnp.where(self.hit & (dot(n, direction) < 0), mat.emission[g], 0.0)
        self.wo = -direction
        # shade two-sided surfaces from the side they are seen from
        self.n = jnp.where(dot(n, self.wo) >= 0, 1.0, -1.0) * n
        self.point = point
        self.material = (mat.diffuse[g], mat.specular[g], mat.roughness[g])
        self.scene = scene
        diffuse, specular, roughness = self.material
        # BRDF sampling: the glossy lobe with probability k_s / (k_s + mean k_d), else cosine
        p_glossy = _brdf.specular_probability(diffuse, specular)
        self.brdf = DirectionMixture(
            (BeckmannLobe(self.n, self.wo, roughness), CosineHemisphere(self.n)),
            jnp.stack([p_glossy, 1.0 - p_glossy]),
        )

    def brdf_cos(self, wi):
        f = _brdf.evaluate(*self.material, self.n, self.wo, wi)
        return f * jnp.maximum(dot(self.n, wi), 0.0)

    def sample_light(self, u):
        """A light chosen uniformly (re-using `u[0]`) and a direction towards it: `(wi, g)`."""
        g, u = _pick_light(self.scene, u)
        sphere, quad = _light_proposals(self.scene, self.point, g)
        ns = len(self.scene.spheres)
        wi = jnp.zeros(3)
        if sphere is not None:
            wi = jnp.where(g < ns, sphere.warp(u)[0], wi)
        if quad is not None:
            wi = jnp.where(g >= ns, quad.warp(u)[0], wi)
        return wi, g

    def light_pdf(self, wi, g, t, origin):
        """Density of `sample_light` at `wi`, whose ray from `origin` first hits shape `g` at `t`.

        The density of the light hit (times the probability of choosing it), 0
        if `g` is not a light: the tracer has decided the hit, so the light's
        `pdf_on_hit` is used, with the distance from the shading point.
        """
        scene = self.scene
        ns = len(scene.spheres)
        sphere, quad = _light_proposals(scene, self.point, g)
        distance = _distance(self.point, origin, wi, t)
        p = jnp.zeros(())
        if sphere is not None:
            p = jnp.where(g < ns, sphere.pdf_on_hit(wi, distance), p)
        if quad is not None:
            p = jnp.where(g >= ns, quad.pdf_on_hit(wi, distance), p)
        n_shapes = ns + len(scene.quads) + len(scene.planes)
        is_light = jnp.zeros(n_shapes, bool).at[jnp.asarray(scene.lights)].set(True)
        return jnp.where((g >= 0) & is_light[jnp.maximum(g, 0)], p * (1.0 / len(scene.lights)), 0.0)

    def light_technique(self, u):
        """`(f cos L_e, p_L, p_B)` for a light-sampled direction (shadow ray included)."""
        wi, light = self.sample_light(u)
        origin = offset(self.point, self.n, wi)
        le, g, t = self.scene.trace_emission(origin, wi)
        le = jnp.where(g == light, le, 0.0)  # occluded: something else is hit first
        p_l = self.light_pdf(wi, g, t, origin)
        return self.brdf_cos(wi) * le, p_l, self.brdf.pdf(wi)

    def direction_technique(self, wi, p):
        """`(f cos L_e, p_L, p)` for a direction drawn by a non-light technique with density `p`."""
        origin = offset(self.point, self.n, wi)
        le, g, t = self.scene.trace_emission(origin, wi)
        return self.brdf_cos(wi) * le, self.light_pdf(wi, g, t, origin), p

    def brdf_technique(self, u):
        return self.direction_technique(*self.brdf.warp(u))


def _direct(shading: _Shading, strategy: str, ua, ub):
    """Reflected direct light for one camera sample; `ua`, `ub` are `(2,)` (or `(2, 2)`) points."""
    if strategy == "light":
        f, p_l, _ = shading.light_technique(ua)
        return safe_div(f, p_l)
    if strategy == "brdf":
        f, _, p_b = shading.brdf_technique(ua)
        return safe_div(f, p_b)
    if strategy.startswith(("mis_balance", "mis_power")):
        heuristic = "balance" if strategy.startswith("mis_balance") else "power"
        f_l, p_ll, p_lb = shading.light_technique(ua)
        f_b, p_bl, p_bb = shading.brdf_technique(ub)

        def weight(pdfs):
            # the first technique's; power heuristic in ratio form with an int beta (p * p)
            return mis_weights(pdfs, heuristic, 2, form="ratio", technique=0)

        light = weight((p_ll, p_lb)) * safe_div(f_l, p_ll)
        brdf = weight((p_bb, p_bl)) * safe_div(f_b, p_bb)
        if strategy.endswith(_PARTS):
            return jnp.stack([light, brdf])
        return light + brdf
    if strategy == "mis_one_sample":
        c = ONE_SAMPLE_LIGHT_PROBABILITY

        def one(u):
            # pick the technique with the first coordinate, then draw with the rest of it
            use_light = u[0] < c
            u0 = jnp.where(use_light, u[0] / c, (u[0] - c) / (1.0 - c))
            v = jnp.stack([jnp.clip(u0, 0.0, 1.0 - 1e-7), u[1]])
            wi_light, light = shading.sample_light(v)
            wi_brdf = shading.brdf.warp(v)[0]
            wi = jnp.where(use_light, wi_light, wi_brdf)
            origin = offset(shading.point, shading.n, wi)
            le, g, t = shading.scene.trace_emission(origin, wi)
            le = jnp.where(use_light & (g != light), 0.0, le)
            den = c * shading.light_pdf(wi, g, t, origin) + (1.0 - c) * shading.brdf.pdf(wi)
            return safe_div(shading.brdf_cos(wi) * le, den)

        return 0.5 * (one(ua[0]) + one(ua[1]))
    if strategy in ("hemisphere_uniform", "hemisphere_cosine"):
        kind = UniformHemisphere if strategy == "hemisphere_uniform" else CosineHemisphere
        f, _, p = shading.direction_technique(*kind(shading.n).warp(ua))
        return safe_div(f, p)
    raise AssertionError(strategy)


def _pixel(key, scene: Scene, index, strategy: str, spp: int, width: int, height: int, points):
    key = jax.random.fold_in(key, index)
    n_a = 2 * spp if strategy == "mis_one_sample" else spp
    two = strategy.startswith(("mis_balance", "mis_power"))
    if points == "uniform":
        # one draw for jitter and directions: fewer PRNG calls in the graph, faster compiles
        u = jax.random.uniform(key, (spp, 6))
        jitter, ua, ub = u[:, 0:2], u[:, 2:4], u[:, 4:6]
        if strategy == "mis_one_sample":
            ua = u[:, 2:6]
    else:
        k_jitter, k_a, k_b = jax.random.split(key, 3)
        jitter = jax.random.uniform(k_jitter, (spp, 2))
        ua = point_set(points, k_a, n_a)
        ub = point_set(points, k_b, spp) if two else ua
    if strategy == "mis_one_sample":
        ua = ua.reshape(spp, 2, 2)
    if not two:
        ub = ua
    xy = jnp.stack([index % width, index // width]).astype(float) + jitter

    def sample(xy, ua, ub):
        origin, direction = scene.camera.ray(xy, width, height)
        shading = _Shading(scene, origin, direction)
        direct = jnp.where(shading.hit, _direct(shading, strategy, ua, ub), 0.0)
        if strategy.endswith(_PARTS):
            return jnp.concatenate([shading.emitted[None], direct])
        return shading.emitted + direct

    return jnp.mean(jax.vmap(sample)(xy, ua, ub), axis=0)


@functools.partial(
    jax.jit, static_argnames=("strategy", "spp", "width", "height", "points", "batch")
)
def _render(key, scene, *, strategy, spp, width, height, points, batch):
    indices = jnp.arange(width * height)
    pixel = lambda i: _pixel(key, scene, i, strategy, spp, width, height, points)
    image = jax.lax.map(pixel, indices, batch_size=min(batch, width * height))
    return image.reshape(height, width, *image.shape[1:])


def check_strategy(scene: Scene, strategy: str) -> None:
    if strategy not in STRATEGIES:
        raise ValueError(f"`strategy` must be one of {STRATEGIES}, got {strategy!r}.")
    if strategy not in scene.strategies:
        raise ValueError(
            f"`strategy` {strategy!r} is not available for this scene; it supports {scene.strategies}."
        )


def render(
    key,
    scene: Scene,
    *,
    strategy: str,
    spp: int,
    width: int,
    height: int,
    points: str = "uniform",
    max_samples_per_batch: int = 1 << 16,
):
    r"""Render `scene` with direct lighting; returns linear RGB of shape `(height, width, 3)`.

    **Arguments:**

    - `key`: a PRNG key; pixel `i` uses `fold_in(key, i)`, so the image does
      not depend on how pixels are batched.
    - `scene`: a `Scene`, e.g. `scenes.veach_mis()` or `scenes.area_light()`.
    - `strategy`: `"light"`, `"brdf"`, `"mis_balance"`, `"mis_power"`,
      `"mis_one_sample"`, or (where the scene lists them)
      `"hemisphere_uniform"`, `"hemisphere_cosine"`.
    - `spp`: samples per pixel per technique (an MIS sample is one light and
      one BRDF sample; one-sample MIS takes two draws).
    - `width`, `height`: image size in pixels.
    - `points`: the 2-D pattern of each pixel's direction samples —
      `"uniform"`, `"stratified"` (jittered grid, the most square `a × b = spp`),
      `"latin_hypercube"` or `"halton"` (randomised per pixel).
    - `max_samples_per_batch`: pixels are vmapped in batches of about this many
      samples (`lax.map`), bounding memory.

    **Returns:** the image as an array `(height, width, 3)`.

    !!! Example

        ```python
        import jax
        from jaxmc.render import render, scenes
        image = render(jax.random.key(0), scenes.veach_mis(), strategy="mis_power",
                       spp=4, width=48, height=32)
        ```
    """
    key = check_key(key)
    if not isinstance(scene, Scene):
        raise TypeError(f"`scene` must be a jaxmc.render Scene, got {type(scene).__name__}.")
    check_strategy(scene, strategy)
    if points not in POINT_SETS:
        raise ValueError(f"`points` must be one of {POINT_SETS}, got {points!r}.")
    spp = check_count(spp, "spp")
    width = check_count(width, "width")
    height = check_count(height, "height")
    batch = max(1, check_count(max_samples_per_batch, "max_samples_per_batch") // spp)
    return _render(
        key,
        scene,
        strategy=strategy,
        spp=spp,
        width=width,
        height=height,
        points=points,
        batch=batch,
    )


def mis_parts(
    key,
    scene: Scene,
    *,
    heuristic: str = "balance",
    spp: int,
    width: int,
    height: int,
    points: str = "uniform",
    max_samples_per_batch: int = 1 << 16,
):
    r"""The terms of multi-sample MIS kept apart: `(emitted, light, brdf)`, each `(H, W, 3)`.

    `emitted` is the emission seen directly, `light` the weighted light-sampling
    term $w_L f L_e \cos\theta / p_L$, `brdf` the weighted BRDF-sampling term;
    their sum is `render(..., strategy="mis_" + heuristic)` for the same key.
    `light / (light + brdf)` shows where the heuristic trusts light sampling
    (Veach's thesis, fig. 9.2).
    """
    if heuristic not in ("balance", "power"):
        raise ValueError(f"`heuristic` must be 'balance' or 'power', got {heuristic!r}.")
    key = check_key(key)
    strategy = "mis_" + heuristic
    check_strategy(scene, strategy)
    if points not in POINT_SETS:
        raise ValueError(f"`points` must be one of {POINT_SETS}, got {points!r}.")
    spp = check_count(spp, "spp")
    batch = max(1, check_count(max_samples_per_batch, "max_samples_per_batch") // spp)
    image = _render(
        key,
        scene,
        strategy=strategy + _PARTS,
        spp=spp,
        width=check_count(width, "width"),
        height=check_count(height, "height"),
        points=points,
        batch=batch,
    )
    return image[..., 0, :], image[..., 1, :], image[..., 2, :]


def object_ids(scene: Scene, width: int, height: int):
    """Global index of the shape seen through each pixel centre, `(height, width)`; -1 for none."""
    width = check_count(width, "width")
    height = check_count(height, "height")
    ys, xs = jnp.meshgrid(jnp.arange(height) + 0.5, jnp.arange(width) + 0.5, indexing="ij")

    def one(x, y):
        origin, direction = scene.camera.ray(jnp.stack([x, y]), width, height)
        t, g = scene.intersect(origin, direction)
        return jnp.where(jnp.isfinite(t), g, -1)

    return jax.jit(jax.vmap(jax.vmap(one)))(xs, ys)
