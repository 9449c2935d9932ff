r"""Direction proposals at a shading point: densities over unit directions $\omega \in S^2$.

Each is an equinox Module (a pytree: it passes through `jit`, and `vmap` over
shading points) whose density is with respect to solid angle, the measure of
the lighting integral

$$ L(x, \omega_o) = \int_{S^2} f(\omega_o, \omega)\, L_e(x, \omega)\, \cos^+\theta\, d\omega .$$

They follow jaxmc's proposal protocol, so they go straight into
`jaxmc.importance`, `jaxmc.mis` and `jaxmc.mis_one_sample`:

- `sample(key, n) -> (ω, pdf)`, `ω` of shape `(n, 3)`, `pdf` of shape `(n,)`;
- `pdf(ω)`, `log_pdf(ω)`: a batch `(n, 3) -> (n,)` or one direction `(3,) -> ()`;
- `warp(u) -> (ω, pdf)`: the deterministic map behind `sample`, from points
  `u` of shape `(..., 2)` in $[0,1)^2$, for stratified or low-discrepancy
  patterns (the renderer's `points=`).

| proposal | density $p(\omega)$ |
| --- | --- |
| `CosineHemisphere(normal)` | $\max(\cos\theta, 0)/\pi$ |
| `UniformHemisphere(normal)` | $1/2\pi$ above the surface |
| `SphereLight(center, radius, ref)` | $1/(2\pi(1 - \cos\theta_{max}))$ inside the cone the sphere subtends |
| `QuadLight(corner, edge_u, edge_v, ref)` | $t^2/(A\,\lvert\cos\theta_l\rvert)$ along rays that hit the quad |
| `BeckmannLobe(normal, wo, roughness)` | $D(h)\cos\theta_h / (4\,\lvert\omega_o\cdot h\rvert)$ |
| `DirectionMixture(components, weights)` | $\sum_k w_k p_k(\omega)$ |

They are not `jaxmc.proposals.AbstractProposal`s: those are densities on a box
$[lo, hi] \subset \mathbb{R}^d$ with respect to Lebesgue measure, which `fit`,
`adapt` and `integrate` map from the unit cube; a direction density lives on
the sphere and has no box. The estimators only need the protocol above.
"""

from __future__ import annotations

import abc
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _random, warps
from .._checks import check_count, check_key, is_concrete
from ._brdf import beckmann_d
from ._math import dot, normalize, reflect, safe_div, safe_sqrt, to_world


def _vector(x, name: str, what: str) -> jax.Array:
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    if x.shape != (3,):
        raise ValueError(
            f"`{name}` must be {what}, a 3-vector of shape (3,), got shape {x.shape}. "
            "A proposal describes one shading point: use jax.vmap for many."
        )
    return x


def _unit_vector(x, name: str) -> jax.Array:
    x = _vector(x, name, "a unit vector")
    if is_concrete(x) and abs(float(np.linalg.norm(np.asarray(x, np.float64))) - 1.0) > 1e-3:
        raise ValueError(f"`{name}` must be a unit vector, got {np.asarray(x)} (norm != 1).")
    return x


def _positive(x, name: str) -> jax.Array:
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    if x.shape != ():
        raise ValueError(f"`{name}` must be a scalar, got shape {x.shape}.")
    if is_concrete(x) and not float(x) > 0:
        raise ValueError(f"`{name}` must be > 0, got {float(x)}.")
    return x


def _directions(w) -> jax.Array:
    w = jnp.asarray(w)
    if w.ndim == 0 or w.shape[-1] != 3:
        raise ValueError(
            f"`w` must be a direction of shape (3,) or a batch (n, 3), got shape {w.shape}."
        )
    return w


def _units(u) -> jax.Array:
    u = jnp.asarray(u)
    if u.ndim == 0 or u.shape[-1] != 2:
        raise ValueError(f"`u` must have shape (..., 2) (points of [0,1)^2), got shape {u.shape}.")
    return u


class AbstractDirections(eqx.Module):
    """Base class of the direction proposals: a density over unit 3-vectors w.r.t. solid angle.

    Subclasses implement `warp` and `pdf`; `sample` draws `u` uniform on
    $(0,1)^2$ and warps it, `log_pdf` is $\\log p$ ($-\\infty$ where $p = 0$).

    !!! Example

        ```python
        import jax, jax.numpy as jnp, jaxmc
        from jaxmc.render import CosineHemisphere, SphereLight

        center, point, normal = jnp.array([1.0, 0.0, 3.0]), jnp.zeros(3), jnp.array([0.0, 0.0, 1.0])
        light = SphereLight(center, 1.0, point)  # radius 1 at distance √10
        hits = lambda w: w @ center / jnp.sqrt(10.0) >= jnp.sqrt(0.9)  # cos θmax = √(1 - 1/10)
        f = lambda w: jnp.maximum(w @ normal, 0.0) / jnp.pi * hits(w)  # white Lambertian, L = 1
        est = jaxmc.mis(jax.random.key(0), f, [light, CosineHemisphere(normal)], (64, 64))
        # est.mean ≈ sin²θmax cos α = 0.1 · 3/√10
        ```
    """

    @abc.abstractmethod
    def warp(self, u: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Map `u` of shape `(..., 2)` in $[0,1)^2$ to directions `(..., 3)` and their density `(...)`."""

    @abc.abstractmethod
    def pdf(self, w: jax.Array) -> jax.Array:
        """Solid-angle density at unit directions: `(n, 3) -> (n,)` or `(3,) -> ()`; 0 off the support."""

    def _dtype(self):
        leaves = [x for x in jax.tree_util.tree_leaves(self) if jnp.issubdtype(x.dtype, jnp.floating)]
        return jnp.result_type(*leaves) if leaves else jnp.result_type(float)

    def log_pdf(self, w: jax.Array) -> jax.Array:
        """$\\log p(\\omega)$, $-\\infty$ where the density is 0."""
        p = self.pdf(w)
        positive = p > 0
        return jnp.where(positive, jnp.log(jnp.where(positive, p, 1.0)), -jnp.inf)

    def sample(self, key: jax.Array, n: int) -> tuple[jax.Array, jax.Array]:
        """Draw `n` directions; returns `(ω, pdf(ω))` of shapes `(n, 3)` and `(n,)`."""
        key = check_key(key)
        n = check_count(n)
        return self.warp(_random.uniform(key, (n, 2), self._dtype()))


class CosineHemisphere(AbstractDirections):
    r"""Cosine-weighted directions about a unit `normal`: $p(\omega) = \max(\cos\theta, 0)/\pi$.

    $\cos\theta = n\cdot\omega$; zero below the horizon. The ideal proposal for a
    Lambertian surface under uniform light (Malley's method, `warps.hemisphere_cosine`).

    **Arguments:** `normal`, a unit vector of shape `(3,)`.
    """

    normal: jax.Array

    def __init__(self, normal):
        self.normal = _unit_vector(normal, "normal")

    def warp(self, u):
        w = to_world(warps.hemisphere_cosine(_units(u)), self.normal)
        return w, self.pdf(w)

    def pdf(self, w):
        return jnp.maximum(dot(self.normal, _directions(w)), 0.0) / jnp.pi


class UniformHemisphere(AbstractDirections):
    r"""Uniform directions about a unit `normal`: $p(\omega) = 1/2\pi$ for $n\cdot\omega \ge 0$, else 0.

    **Arguments:** `normal`, a unit vector of shape `(3,)`.
    """

    normal: jax.Array

    def __init__(self, normal):
        self.normal = _unit_vector(normal, "normal")

    def warp(self, u):
        w = to_world(warps.hemisphere_uniform(_units(u)), self.normal)
        return w, self.pdf(w)

    def pdf(self, w):
        return jnp.where(dot(self.normal, _directions(w)) >= 0, 1.0 / (2.0 * jnp.pi), 0.0)


class SphereLight(AbstractDirections):
    r"""Directions from the shading point `ref` towards a sphere (`center`, `radius`),
    uniform in the cone it subtends.

    Seen from distance $d$ the sphere fills the cone about $(c - ref)/d$ with
    $\sin\theta_{max} = r/d$, so

    $$ p(\omega) = \frac{1}{2\pi(1 - \cos\theta_{max})} \text{ inside the cone, 0 outside;} $$

    every sampled ray hits the sphere (`warps.sphere_solid_angle`, with
    $1 - \cos\theta_{max}$ free of cancellation for tiny lights). From inside the
    sphere the cone is the whole sphere of directions, $p = 1/4\pi$.

    **Arguments:**

    - `center`: the sphere's centre, shape `(3,)`.
    - `radius`: its radius, $> 0$.
    - `ref`: the shading point, shape `(3,)`.
    """

    center: jax.Array
    radius: jax.Array
    ref: jax.Array

    def __init__(self, center, radius, ref):
        self.center = _vector(center, "center", "the sphere's centre")
        self.radius = _positive(radius, "radius")
        self.ref = _vector(ref, "ref", "the shading point")

    def warp(self, u):
        w = warps.sphere_solid_angle(_units(u), self.center, self.radius, self.ref)
        return w, jnp.broadcast_to(self.pdf_on_hit(w, None), w.shape[:-1])

    def pdf(self, w):
        return warps.sphere_solid_angle_pdf(_directions(w), self.center, self.radius, self.ref)

    def pdf_on_hit(self, w, distance):
        r"""The density along a ray known to hit the sphere: $1/(2\pi(1 - \cos\theta_{max}))$.

        A ray tracer that found the hit already knows the direction is in the
        cone; this skips the cone test (which, at the rim, need not agree with
        the tracer's own intersection). `w` and `distance` are not needed.
        """
        del w, distance
        return warps.sphere_solid_angle_pdf(self.center - self.ref, self.center, self.radius, self.ref)


class QuadLight(AbstractDirections):
    r"""Directions from the shading point `ref` towards a parallelogram light
    `corner + a·edge_u + b·edge_v`, $a, b \in [0, 1]$, sampled uniformly by area.

    A uniform point $y$ on the quad ($p_A = 1/A$, $A = |e_u \times e_v|$) seen
    at distance $t = |y - ref|$ under $\cos\theta_l = n_l\cdot\omega$ has the
    solid-angle density (PBRT 3rd ed. §5.5.3)

    $$ p(\omega) = \frac{t^2}{A\,|\cos\theta_l|} $$

    for directions whose ray from `ref` meets the quad, 0 otherwise. Both faces
    count: which side emits is the integrand's business.

    **Arguments:**

    - `corner`: a corner of the quad, shape `(3,)`.
    - `edge_u`, `edge_v`: its two edges from `corner`, shape `(3,)`, not parallel.
    - `ref`: the shading point, shape `(3,)`.
    """

    corner: jax.Array
    edge_u: jax.Array
    edge_v: jax.Array
    ref: jax.Array

    def __init__(self, corner, edge_u, edge_v, ref):
        self.corner = _vector(corner, "corner", "a corner of the quad")
        self.edge_u = _vector(edge_u, "edge_u", "an edge of the quad")
        self.edge_v = _vector(edge_v, "edge_v", "an edge of the quad")
        self.ref = _vector(ref, "ref", "the shading point")
        if is_concrete(self.edge_u) and is_concrete(self.edge_v):
            if not np.linalg.norm(np.cross(np.asarray(self.edge_u), np.asarray(self.edge_v))) > 0:
                raise ValueError("`edge_u` and `edge_v` must span a parallelogram of non-zero area.")

    @property
    def area(self):
        return jnp.linalg.norm(jnp.cross(self.edge_u, self.edge_v))

    @property
    def light_normal(self):
        """Unit normal $e_u \\times e_v / A$."""
        return normalize(jnp.cross(self.edge_u, self.edge_v))

    def warp(self, u):
        u = _units(u)
        y = self.corner + u[..., 0:1] * self.edge_u + u[..., 1:2] * self.edge_v
        w = normalize(y - self.ref)
        return w, self.pdf_on_hit(w, jnp.linalg.norm(y - self.ref, axis=-1))

    def pdf(self, w):
        w = _directions(w)
        m = jnp.cross(self.edge_u, self.edge_v)
        denom = dot(m, w)
        t = safe_div(dot(m, self.corner - self.ref), denom)
        rel = self.ref + t[..., None] * w - self.corner
        # coordinates along the edges by the dual basis: a = (rel x v)·m / |m|^2
        mm = dot(m, m)
        a = dot(jnp.cross(rel, self.edge_v), m) / mm
        b = dot(jnp.cross(self.edge_u, rel), m) / mm
        hit = (denom != 0) & (t > 0) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)
        return jnp.where(hit, self.pdf_on_hit(w, t), 0.0)

    def pdf_on_hit(self, w, distance):
        r"""The density along a ray known to meet the quad at `distance`: $t^2/(A|n_l\cdot\omega|)$.

        For a ray tracer that has found the hit (and so knows the distance);
        `pdf` intersects the quad itself.
        """
        cos_l = jnp.abs(dot(self.light_normal, w))
        return safe_div(distance * distance, self.area * cos_l)


class BeckmannLobe(AbstractDirections):
    r"""The glossy lobe of the renderer's plates: a Beckmann microfacet normal $h$
    drawn about `normal` with density $D(h)\cos\theta_h$, and $\omega$ the mirror
    image of `wo` (the direction towards the viewer) about $h$.

    $$ D(h) = \frac{e^{-\tan^2\theta_h/\alpha^2}}{\pi\alpha^2\cos^4\theta_h}, \qquad
       p(\omega) = \frac{D(h)\cos\theta_h}{4\,|\omega_o\cdot h|}, $$

    $\alpha$ = `roughness`, $h$ the half vector $\pm(\omega + \omega_o)/|\omega + \omega_o|$
    on the side of `normal` ($4|\omega_o\cdot h|$ is the Jacobian of the reflection).
    Sampling: $\tan^2\theta_h = -\alpha^2\log(1 - u_1)$, $\phi_h = 2\pi u_2$.
    The density is over the whole sphere: near grazing `wo`, some reflected
    directions fall below the surface, where a BRDF is zero.

    **Arguments:**

    - `normal`: the surface normal, a unit vector of shape `(3,)`.
    - `wo`: the unit direction towards the viewer, shape `(3,)`.
    - `roughness`: the Beckmann $\alpha > 0$ (RMS slope of the microfacets).
    """

    normal: jax.Array
    wo: jax.Array
    roughness: jax.Array

    def __init__(self, normal, wo, roughness):
        self.normal = _unit_vector(normal, "normal")
        self.wo = _unit_vector(wo, "wo")
        self.roughness = _positive(roughness, "roughness")

    def _half_vector(self, u):
        tan_t = self.roughness * safe_sqrt(-jnp.log1p(-u[..., 0]))
        cos_t = 1.0 / jnp.sqrt(1.0 + tan_t * tan_t)
        sin_t = tan_t * cos_t
        phi = 2.0 * jnp.pi * u[..., 1]
        local = jnp.stack([sin_t * jnp.cos(phi), sin_t * jnp.sin(phi), cos_t], axis=-1)
        return to_world(local, self.normal)

    def warp(self, u):
        w = reflect(self.wo, self._half_vector(_units(u)))
        return w, self.pdf(w)

    def pdf(self, w):
        h = normalize(_directions(w) + self.wo)
        h = jnp.where(dot(h, self.normal)[..., None] < 0, -h, h)
        d = beckmann_d(h, self.normal, self.roughness)
        return safe_div(d * dot(h, self.normal), 4.0 * jnp.abs(dot(self.wo, h)))


class DirectionMixture(AbstractDirections):
    r"""A mixture $p(\omega) = \sum_k w_k\, p_k(\omega)$ of direction proposals.

    `warp` picks component $k$ with the first coordinate,
    $C_k \le u_1 < C_{k+1}$ ($C_k = \sum_{j<k} w_j$), rescales it to
    $(u_1 - C_k)/w_k \in [0, 1)$ and warps with component $k$; so stratified or
    low-discrepancy `u` stay well spread within each component. The renderer's
    BRDF sampling is `DirectionMixture((BeckmannLobe(...), CosineHemisphere(n)),
    (p_s, 1 - p_s))` with $p_s = k_s/(k_s + \bar k_d)$.

    **Arguments:**

    - `components`: a sequence of direction proposals (anything with `warp` and `pdf`).
    - `weights`: shape `(k,)`, $\ge 0$, summing to 1.
    """

    components: tuple
    weights: jax.Array

    def __init__(self, components: Sequence, weights):
        if isinstance(components, AbstractDirections) or not isinstance(components, Sequence):
            raise TypeError("`components` must be a sequence of direction proposals.")
        components = tuple(components)
        if not components or not all(
            callable(getattr(c, "warp", None)) and callable(getattr(c, "pdf", None))
            for c in components
        ):
            raise TypeError("`components` must be a non-empty sequence of objects with warp and pdf.")
        weights = jnp.asarray(weights)
        if not jnp.issubdtype(weights.dtype, jnp.floating):
            weights = weights.astype(jnp.result_type(float))
        if weights.shape != (len(components),):
            raise ValueError(
                f"`weights` must have one entry per component, shape ({len(components)},), "
                f"got shape {weights.shape}."
            )
        if is_concrete(weights):
            wts = np.asarray(weights, np.float64)
            if np.any(wts < 0) or abs(wts.sum() - 1.0) > 1e-5:
                raise ValueError(f"`weights` must be >= 0 and sum to 1, got {wts}.")
        self.components, self.weights = components, weights

    def warp(self, u):
        u = _units(u)
        u0 = u[..., 0]
        # running sums one add at a time, so two components rescale by (u0 - w0) / w1 exactly
        lower, start = [], jnp.zeros((), self.weights.dtype)
        for k in range(len(self.components)):
            lower.append(start)
            start = start + self.weights[k]
        index = sum((u0 >= lower[k]).astype(jnp.int32) for k in range(1, len(lower)))
        rescaled = jnp.zeros_like(u0)
        for k in range(len(self.components)):
            rescaled = jnp.where(index == k, safe_div(u0 - lower[k], self.weights[k]), rescaled)
        # rounding may give exactly 1: keep it below, as every warp expects [0, 1)
        top = 1.0 - jnp.finfo(u.dtype).eps
        v = jnp.stack([jnp.clip(rescaled, 0.0, top), u[..., 1]], axis=-1)
        w = jnp.zeros(u.shape[:-1] + (3,), u.dtype)
        for k, component in enumerate(self.components):
            w = jnp.where((index == k)[..., None], component.warp(v)[0], w)
        return w, self.pdf(w)

    def pdf(self, w):
        w = _directions(w)
        total = self.weights[0] * self.components[0].pdf(w)
        for k in range(1, len(self.components)):
            total = total + self.weights[k] * self.components[k].pdf(w)
        return total
