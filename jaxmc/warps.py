r"""Warps: maps from the unit cube $[0,1)^k$ to other domains (lecture §3.1).

Every warp is the *inversion method* of lecture §3.1: write the target density
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

References: lecture §3.1 (inversion; examples 3.1.1 power, 3.1.2 exponential,
3.1.3 disk); P. Shirley and K. Chiu, "A Low Distortion Map Between Disk and
Square", JGT 1997 (concentric disk); M. Pharr, W. Jakob, G. Humphreys,
*Physically Based Rendering*, §13.6 (hemisphere, cone, triangle and
sphere-light sampling); T. Duff et al., "Building an Orthonormal Basis,
Revisited", JCGT 2017.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from ._checks import is_concrete


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

_TWO_PI = 2.0 * math.pi
_INV_PI = 1.0 / math.pi


# ---------------------------------------------------------------------------
# helpers


def _float(x: ArrayLike) -> jax.Array:
    """`x` as a floating array (integers become the default float dtype)."""
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


def _point(x: ArrayLike, k: int, name: str, what: str) -> jax.Array:
    """A floating array whose last axis has length `k` (one point of `what`)."""
    x = _float(x)
    if x.ndim == 0 or x.shape[-1] != k:
        raise ValueError(
            f"`{name}` must have shape (..., {k}) ({what}), got shape {x.shape}. "
            "Warps are written for one point; leading axes are batch axes."
        )
    return x


def _check_concrete(ok, message: str, *values) -> None:
    """Raise `ValueError(message)` if all `values` are concrete and `ok(*values)` fails."""
    if all(is_concrete(v) for v in values):
        arrays = [np.asarray(v) for v in values]
        if not np.all(ok(*arrays)):
            raise ValueError(message.format(*arrays))


def _stack(*components: jax.Array) -> jax.Array:
    components = jnp.broadcast_arrays(*components)
    return jnp.stack(components, axis=-1)


def _wrap_angle(phi: jax.Array) -> jax.Array:
    """An angle from `atan2` (in $(-\\pi, \\pi]$) as a fraction of a turn in $[0, 1)$."""
    t = phi / _TWO_PI
    t = jnp.where(t < 0, t + 1.0, t)
    return jnp.where(t >= 1.0, t - 1.0, t)


def _frame(n: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Tangents `(t, b)` completing the unit vector `n` to a right-handed frame.

    Branch-free construction of Duff et al. (JCGT 2017); stable for all `n`,
    including $n = \\pm z$.
    """
    x, y, z = n[..., 0], n[..., 1], n[..., 2]
    sign = jnp.where(z >= 0, 1.0, -1.0).astype(n.dtype)
    a = -1.0 / (sign + z)
    b = x * y * a
    t = _stack(1.0 + sign * x * x * a, sign * b, -sign * x)
    s = _stack(b, sign + y * y * a, -y)
    return t, s


# ---------------------------------------------------------------------------
# box


def box(u: ArrayLike, lo: ArrayLike, hi: ArrayLike) -> jax.Array:
    r"""Uniform point in the box $[lo, hi]$: $x = lo + u\,(hi - lo)$.

    The density is constant, $p(x) = 1/V$ with $V = \prod_j (hi_j - lo_j)$, so
    the CDF of each coordinate is $(x_j - lo_j)/(hi_j - lo_j)$ and its inverse
    is the affine map above (lecture §3.1).

    **Arguments:**

    - `u`: shape `(..., k)`, points of $[0,1)^k$.
    - `lo`, `hi`: scalars or shape `(k,)` (or broadcastable to `u`), `lo < hi`.

    **Returns:** points of shape `(..., k)`.
    """
    u = _float(u)
    if u.ndim == 0:
        raise ValueError("`u` must have shape (..., k), got a scalar. Use shape (1,) for 1-D.")
    lo, hi = _float(lo), _float(hi)
    _check_concrete(lambda a, b: a < b, "`lo` must be < `hi`, got lo={}, hi={}.", lo, hi)
    u, lo, hi = jnp.broadcast_arrays(u, lo, hi)
    return lo + u * (hi - lo)


def box_pdf(x: ArrayLike, lo: ArrayLike, hi: ArrayLike) -> jax.Array:
    """Density of `box`: $1/\\prod_j (hi_j - lo_j)$ inside the box, 0 outside; shape `x.shape[:-1]`."""
    x = _float(x)
    if x.ndim == 0:
        raise ValueError("`x` must have shape (..., k), got a scalar.")
    x, lo, hi = jnp.broadcast_arrays(x, _float(lo), _float(hi))
    inside = jnp.all((x >= lo) & (x <= hi), axis=-1)
    return jnp.where(inside, 1.0 / jnp.prod(hi - lo, axis=-1), 0.0)


def box_inverse(x: ArrayLike, lo: ArrayLike, hi: ArrayLike) -> jax.Array:
    """Inverse of `box`: $u = (x - lo)/(hi - lo)$."""
    x, lo, hi = jnp.broadcast_arrays(_float(x), _float(lo), _float(hi))
    return (x - lo) / (hi - lo)


# ---------------------------------------------------------------------------
# power (lecture §3.1.1)


def power(u: ArrayLike, n: ArrayLike) -> jax.Array:
    r"""Sample $p(x) = (n+1)\,x^n$ on $[0, 1]$ (lecture §3.1.1).

    Normalising $p(x) = c\,x^n$ gives $c = n + 1$; the CDF is
    $P(x) = x^{n+1}$, so inversion gives $X = U^{1/(n+1)}$. Used for Blinn-type
    lobes $\cos^n$. Differentiable in `n` (for $u > 0$) and `u`.

    **Arguments:**

    - `u`: uniform variate(s) in $[0, 1)$, any shape (the warp is 1-D).
    - `n`: the exponent, $n > -1$; broadcasts with `u`.

    **Returns:** `x` with the broadcast shape of `u` and `n`.
    """
    u, n = _float(u), _float(n)
    _check_concrete(lambda m: m > -1, "`n` must be > -1 (so that x^n is integrable), got {}.", n)
    positive = u > 0
    safe_u = jnp.where(positive, u, 1.0)
    # exp(log(u)/(n+1)) rather than u ** (1/(n+1)): same value, and the gradient
    # in `n` stays finite (0) at u = 0 instead of 0 * inf.
    return jnp.where(positive, jnp.exp(jnp.log(safe_u) / (n + 1.0)), 0.0)


def power_pdf(x: ArrayLike, n: ArrayLike) -> jax.Array:
    """Density $(n+1)\\,x^n$ on $[0, 1]$, 0 outside."""
    x, n = _float(x), _float(n)
    inside = (x >= 0) & (x <= 1)
    safe_x = jnp.where(inside, x, 0.5)
    return jnp.where(inside, (n + 1.0) * safe_x**n, 0.0)


def power_inverse(x: ArrayLike, n: ArrayLike) -> jax.Array:
    """Inverse of `power`: the CDF $u = x^{n+1}$."""
    x, n = _float(x), _float(n)
    return x ** (n + 1.0)


# ---------------------------------------------------------------------------
# exponential (lecture §3.1.2)


def exponential(u: ArrayLike, a: ArrayLike) -> jax.Array:
    r"""Sample $p(x) = a\,e^{-a x}$ on $[0, \infty)$ (lecture §3.1.2).

    Normalising $c\,e^{-ax}$ gives $c = a$; the CDF is $P(x) = 1 - e^{-ax}$ and
    solving $U = 1 - e^{-aX}$ gives $X = -\ln(1 - U)/a$. The lecture then
    replaces $1 - U$ by $U'$ (also uniform), i.e. $X = -\ln U'/a$ (the
    printed "$-U'/a$" drops the logarithm). We keep $1 - U$: it is finite at
    $u = 0$ (for $u \in [0, 1)$) and keeps the map increasing, so stratified
    inputs stay ordered and `exponential_inverse` is the CDF itself.

    **Arguments:**

    - `u`: uniform variate(s) in $[0, 1)$, any shape.
    - `a`: the rate, $a > 0$; broadcasts with `u`.
    """
    u, a = _float(u), _float(a)
    _check_concrete(lambda r: r > 0, "`a` must be > 0, got {}.", a)
    return -jnp.log1p(-u) / a


def exponential_pdf(x: ArrayLike, a: ArrayLike) -> jax.Array:
    """Density $a\\,e^{-a x}$ for $x \\ge 0$, 0 for $x < 0$."""
    x, a = _float(x), _float(a)
    return jnp.where(x >= 0, a * jnp.exp(-a * jnp.maximum(x, 0.0)), 0.0)


def exponential_inverse(x: ArrayLike, a: ArrayLike) -> jax.Array:
    """Inverse of `exponential`: the CDF $u = 1 - e^{-a x}$."""
    x, a = _float(x), _float(a)
    return -jnp.expm1(-a * x)


# ---------------------------------------------------------------------------
# disks (lecture §3.1.3)


def _unit_disk_pdf(x: ArrayLike) -> jax.Array:
    x = _point(x, 2, "x", "a point of the plane")
    inside = jnp.sum(x * x, axis=-1) <= 1.0
    return jnp.where(inside, _INV_PI, 0.0).astype(x.dtype)


def disk_polar(u: ArrayLike) -> jax.Array:
    r"""Uniform point on the unit disk by polar inversion (lecture §3.1.3).

    The uniform density on the disk is $p(x) = 1/\pi$; in polar coordinates
    ($dA = r\,dr\,d\theta$) it is $p(r, \theta) = r/\pi$, with marginal
    $p(r) = 2r$, CDF $P(r) = r^2$, and conditional $p(\theta \mid r) =
    1/2\pi$. Inverting both gives $r = \sqrt{u_1}$, $\theta = 2\pi u_2$
    (taking $r = u_1$ instead crowds points near the centre, Fig. 4).

    **Arguments:** `u` of shape `(..., 2)`. **Returns:** `(..., 2)` points $(x, y)$.
    """
    u = _point(u, 2, "u", "a point of [0,1)^2")
    r = jnp.sqrt(u[..., 0])
    theta = _TWO_PI * u[..., 1]
    return _stack(r * jnp.cos(theta), r * jnp.sin(theta))


def disk_polar_pdf(x: ArrayLike) -> jax.Array:
    """Area density of `disk_polar`: $1/\\pi$ on the unit disk, 0 outside."""
    return _unit_disk_pdf(x)


def disk_polar_inverse(x: ArrayLike) -> jax.Array:
    """Inverse of `disk_polar`: $u = (r^2, \\theta / 2\\pi)$ with $\\theta \\in [0, 2\\pi)$."""
    x = _point(x, 2, "x", "a point of the plane")
    r2 = jnp.sum(x * x, axis=-1)
    return _stack(r2, _wrap_angle(jnp.arctan2(x[..., 1], x[..., 0])))


def disk_concentric(u: ArrayLike) -> jax.Array:
    r"""Uniform point on the unit disk by Shirley and Chiu's concentric map.

    Map $u$ to $a = 2u - 1 \in [-1, 1]^2$ and send concentric squares to
    concentric circles: in the wedge $|a_1| > |a_2|$, $r = a_1$ and
    $\theta = \frac{\pi}{4} a_2 / a_1$; otherwise $r = a_2$ and
    $\theta = \frac{\pi}{2} - \frac{\pi}{4} a_1 / a_2$. The square of
    half-width $s$ (area $4 s^2$) becomes the disk of radius $s$ (area
    $\pi s^2$) and each wedge is stretched uniformly in angle, so the area
    ratio is $\pi/4$ everywhere: the density is uniform, $1/\pi$, like
    `disk_polar`'s (lecture §3.1.3), but the map distorts areas and strata
    much less. Continuous, with a continuous inverse.

    **Arguments:** `u` of shape `(..., 2)`. **Returns:** `(..., 2)` points.
    """
    u = _point(u, 2, "u", "a point of [0,1)^2")
    a = 2.0 * u - 1.0
    a1, a2 = a[..., 0], a[..., 1]
    first = jnp.abs(a1) > jnp.abs(a2)
    safe_a1 = jnp.where(a1 == 0, 1.0, a1)
    safe_a2 = jnp.where(a2 == 0, 1.0, a2)
    r = jnp.where(first, a1, a2)
    theta = jnp.where(
        first,
        (math.pi / 4) * (a2 / safe_a1),
        (math.pi / 2) - (math.pi / 4) * (a1 / safe_a2),
    )
    return _stack(r * jnp.cos(theta), r * jnp.sin(theta))


def disk_concentric_pdf(x: ArrayLike) -> jax.Array:
    """Area density of `disk_concentric`: $1/\\pi$ on the unit disk, 0 outside."""
    return _unit_disk_pdf(x)


def disk_concentric_inverse(x: ArrayLike) -> jax.Array:
    r"""Inverse of `disk_concentric`: a point of the unit disk to $u \in [0,1]^2$.

    With $r = |x|$ and the angle $\phi$ shifted into $[-\pi/4, 7\pi/4)$, the four
    wedges are undone in turn (the forward map's $r$ is signed).
    """
    x = _point(x, 2, "x", "a point of the plane")
    r = jnp.sqrt(jnp.sum(x * x, axis=-1))
    phi = jnp.arctan2(x[..., 1], x[..., 0])
    phi = jnp.where(phi < -math.pi / 4, phi + _TWO_PI, phi)
    k = 4.0 / math.pi
    # Wedge 0: a1 = r, phi = pi/4 a2/a1.  Wedge 1: a2 = r, phi = pi/2 - pi/4 a1/a2.
    # Wedges 2, 3: the same with r -> -r and phi -> phi - pi.
    w0 = phi < math.pi / 4
    w1 = (~w0) & (phi < 3 * math.pi / 4)
    w2 = (~w0) & (~w1) & (phi < 5 * math.pi / 4)
    a1 = jnp.where(
        w0,
        r,
        jnp.where(
            w1,
            r * k * (math.pi / 2 - phi),
            jnp.where(w2, -r, -r * k * (math.pi / 2 - (phi - math.pi))),
        ),
    )
    a2 = jnp.where(
        w0,
        r * k * phi,
        jnp.where(w1, r, jnp.where(w2, -r * k * (phi - math.pi), -r)),
    )
    return _stack((a1 + 1.0) / 2.0, (a2 + 1.0) / 2.0)


# ---------------------------------------------------------------------------
# spheres and hemispheres


def _direction(cos_theta, sin_theta, phi) -> jax.Array:
    return _stack(sin_theta * jnp.cos(phi), sin_theta * jnp.sin(phi), cos_theta)


def _unit(w: ArrayLike, name: str = "w") -> jax.Array:
    return _point(w, 3, name, "a direction, a unit 3-vector")


def hemisphere_uniform(u: ArrayLike) -> jax.Array:
    r"""Uniform direction on the hemisphere around $+z$ (pdf $1/2\pi$, §2.2.3).

    With $p(\omega) = 1/2\pi$ and $d\omega = \sin\theta\,d\theta\,d\phi$,
    $p(\theta, \phi) = \sin\theta / 2\pi$: the marginal of $\theta$ is
    $\sin\theta$ with CDF $1 - \cos\theta$, and $\phi$ is uniform. Inverting
    (and using $1 - u_1 \sim u_1$) gives $\cos\theta = u_1$, $\phi = 2\pi u_2$.

    **Arguments:** `u` of shape `(..., 2)`. **Returns:** unit vectors `(..., 3)`, $z \ge 0$.
    """
    u = _point(u, 2, "u", "a point of [0,1)^2")
    z = u[..., 0]
    sin_theta = jnp.sqrt(jnp.maximum((1.0 - z) * (1.0 + z), 0.0))
    return _direction(z, sin_theta, _TWO_PI * u[..., 1])


def hemisphere_uniform_pdf(w: ArrayLike) -> jax.Array:
    """Solid-angle density of `hemisphere_uniform`: $1/2\\pi$ for $z \\ge 0$, else 0."""
    w = _unit(w)
    return jnp.where(w[..., 2] >= 0, 1.0 / _TWO_PI, 0.0).astype(w.dtype)


def hemisphere_uniform_inverse(w: ArrayLike) -> jax.Array:
    """Inverse of `hemisphere_uniform`: $u = (\\cos\\theta, \\phi/2\\pi)$."""
    w = _unit(w)
    return _stack(w[..., 2], _wrap_angle(jnp.arctan2(w[..., 1], w[..., 0])))


def hemisphere_cosine(u: ArrayLike) -> jax.Array:
    r"""Cosine-weighted direction on the hemisphere around $+z$ (pdf $\cos\theta/\pi$).

    $p(\omega) = \cos\theta/\pi$ (normalised: $\int_{H^2}\cos\theta\,d\omega =
    \pi$) gives $p(\theta) = 2\cos\theta\sin\theta$ with CDF
    $P(\theta) = \sin^2\theta$, so $\sin\theta = \sqrt{u_1}$ and $\phi = 2\pi
    u_2$: exactly the radius of a uniform disk point (lecture §3.1.3). Hence
    Malley's method: sample the unit disk uniformly and project up,
    $z = \sqrt{1 - x^2 - y^2}$. We use `disk_concentric` for the disk, as PBRT
    does, for its low distortion.

    **Arguments:** `u` of shape `(..., 2)`. **Returns:** unit vectors `(..., 3)`, $z \ge 0$.
    """
    d = disk_concentric(u)
    z = jnp.sqrt(jnp.maximum(1.0 - jnp.sum(d * d, axis=-1), 0.0))
    return jnp.concatenate([d, z[..., None]], axis=-1)


def hemisphere_cosine_pdf(w: ArrayLike) -> jax.Array:
    """Solid-angle density of `hemisphere_cosine`: $\\max(\\cos\\theta, 0)/\\pi$."""
    w = _unit(w)
    return jnp.maximum(w[..., 2], 0.0) * _INV_PI


def hemisphere_cosine_inverse(w: ArrayLike) -> jax.Array:
    """Inverse of `hemisphere_cosine`: project to the disk, then invert the concentric map."""
    w = _unit(w)
    return disk_concentric_inverse(w[..., :2])


def sphere_uniform(u: ArrayLike) -> jax.Array:
    r"""Uniform direction on the unit sphere (pdf $1/4\pi$).

    $p(\theta) = \sin\theta / 2$ on $[0, \pi]$ has CDF $(1 - \cos\theta)/2$,
    so $\cos\theta = 1 - 2u_1$; $\phi = 2\pi u_2$ (Archimedes: $z$ is uniform on
    $[-1, 1]$).

    **Arguments:** `u` of shape `(..., 2)`. **Returns:** unit vectors `(..., 3)`.
    """
    u = _point(u, 2, "u", "a point of [0,1)^2")
    z = 1.0 - 2.0 * u[..., 0]
    # sin(theta) = sqrt(1 - z^2) = 2 sqrt(u1 (1 - u1)), without cancellation near the poles.
    sin_theta = 2.0 * jnp.sqrt(jnp.maximum(u[..., 0] * (1.0 - u[..., 0]), 0.0))
    return _direction(z, sin_theta, _TWO_PI * u[..., 1])


def sphere_uniform_pdf(w: ArrayLike) -> jax.Array:
    """Solid-angle density of `sphere_uniform`: $1/4\\pi$."""
    w = _unit(w)
    return jnp.full(w.shape[:-1], 1.0 / (4.0 * math.pi), dtype=w.dtype)


def sphere_uniform_inverse(w: ArrayLike) -> jax.Array:
    """Inverse of `sphere_uniform`: $u = ((1 - z)/2, \\phi/2\\pi)$."""
    w = _unit(w)
    return _stack((1.0 - w[..., 2]) / 2.0, _wrap_angle(jnp.arctan2(w[..., 1], w[..., 0])))


# ---------------------------------------------------------------------------
# cones and sphere lights


def _cone_local(u: jax.Array, one_minus_cos_max: jax.Array) -> jax.Array:
    """Cone sample in its local frame, from $1 - \\cos\\theta_{max}$ (no cancellation)."""
    q = u[..., 0] * one_minus_cos_max  # 1 - cos(theta)
    sin_theta = jnp.sqrt(jnp.maximum(q * (2.0 - q), 0.0))
    return _direction(1.0 - q, sin_theta, _TWO_PI * u[..., 1])


def _cone_pdf_value(one_minus_cos_max: jax.Array) -> jax.Array:
    return 1.0 / (_TWO_PI * one_minus_cos_max)


def cone(u: ArrayLike, cos_max: ArrayLike) -> jax.Array:
    r"""Uniform direction in the cone $\{\omega : \cos\theta \ge \cos\theta_{max}\}$ around $+z$.

    The cone's solid angle is $2\pi(1 - \cos\theta_{max})$, so
    $p(\omega) = 1/(2\pi(1 - \cos\theta_{max}))$, $p(\theta) = \sin\theta /
    (1 - \cos\theta_{max})$ on $[0, \theta_{max}]$, with CDF
    $P(\theta) = (1 - \cos\theta)/(1 - \cos\theta_{max})$. Inverting (lecture
    §3.1): $\cos\theta = 1 - u_1 (1 - \cos\theta_{max})$, $\phi = 2\pi u_2$.
    `cos_max = 0` is `hemisphere_uniform`, `cos_max = -1` is `sphere_uniform`.
    Differentiable in `cos_max`.

    **Arguments:**

    - `u`: shape `(..., 2)`.
    - `cos_max`: $\cos\theta_{max} \in [-1, 1)$, broadcasts over batch axes.

    **Returns:** unit vectors `(..., 3)`.
    """
    u = _point(u, 2, "u", "a point of [0,1)^2")
    cos_max = _float(cos_max)
    _check_concrete(
        lambda c: (c >= -1) & (c < 1), "`cos_max` must be in [-1, 1), got {}.", cos_max
    )
    return _cone_local(u, 1.0 - cos_max)


def cone_pdf(w: ArrayLike, cos_max: ArrayLike) -> jax.Array:
    """Solid-angle density of `cone`: $1/(2\\pi(1 - \\cos\\theta_{max}))$ inside, 0 outside."""
    w = _unit(w)
    cos_max = _float(cos_max)
    return jnp.where(w[..., 2] >= cos_max, _cone_pdf_value(1.0 - cos_max), 0.0)


def cone_inverse(w: ArrayLike, cos_max: ArrayLike) -> jax.Array:
    """Inverse of `cone`: $u = ((1 - \\cos\\theta)/(1 - \\cos\\theta_{max}), \\phi/2\\pi)$."""
    w = _unit(w)
    cos_max = _float(cos_max)
    return _stack(
        (1.0 - w[..., 2]) / (1.0 - cos_max),
        _wrap_angle(jnp.arctan2(w[..., 1], w[..., 0])),
    )


def _sphere_cone(center, radius, ref):
    """Axis and $1 - \\cos\\theta_{max}$ of the cone subtended by a sphere from `ref`.

    $\\sin^2\\theta_{max} = (r/d)^2$ and $1 - \\cos\\theta_{max} = \\sin^2\\theta_{max} /
    (1 + \\cos\\theta_{max})$, accurate for small (distant) lights. From inside the
    sphere every direction hits it: the cone is the whole sphere ($1 - \\cos = 2$).
    """
    center = _point(center, 3, "center", "the sphere's centre")
    ref = _point(ref, 3, "ref", "the reference point")
    radius = _float(radius)
    _check_concrete(lambda r: r > 0, "`radius` must be > 0, got {}.", radius)
    center, ref = jnp.broadcast_arrays(center, ref)
    d = center - ref
    dist2 = jnp.sum(d * d, axis=-1)
    inside = dist2 <= radius * radius
    safe_dist2 = jnp.where(dist2 > 0, dist2, 1.0)
    axis = d / jnp.sqrt(safe_dist2)[..., None]
    axis = jnp.where((dist2 > 0)[..., None], axis, jnp.asarray([0.0, 0.0, 1.0], d.dtype))
    sin2 = jnp.where(inside, 0.0, radius * radius / safe_dist2)
    cos_max = jnp.sqrt(jnp.maximum(1.0 - sin2, 0.0))
    one_minus_cos = jnp.where(inside, 2.0, sin2 / (1.0 + cos_max))
    return axis, one_minus_cos


def sphere_solid_angle(
    u: ArrayLike, center: ArrayLike, radius: ArrayLike, ref: ArrayLike
) -> jax.Array:
    r"""Direction from `ref` towards a sphere light, uniform in the cone it subtends.

    Seen from `ref` at distance $d$ from the centre, a sphere of radius $r$
    fills the cone around $\hat d = (c - ref)/d$ with
    $\sin\theta_{max} = r/d$. Sampling that cone uniformly (`cone`, by
    inversion, lecture §3.1) gives a solid-angle density
    $p(\omega) = 1/(2\pi(1 - \cos\theta_{max}))$ that is constant on the
    light, which is what the solid-angle form of the lighting integral (§2.2.3)
    wants; it is far better than area sampling (eq. 15) for small or distant
    spheres. Every sampled ray hits the sphere. If `ref` is inside the sphere
    the cone is the whole sphere of directions ($p = 1/4\pi$).
    $1 - \cos\theta_{max}$ is computed without cancellation, so tiny lights
    work in float32. Differentiable in `center`, `radius` and `ref`.

    **Arguments:**

    - `u`: shape `(..., 2)`.
    - `center`: the sphere's centre, shape `(..., 3)`.
    - `radius`: the sphere's radius, $> 0$.
    - `ref`: the shading point, shape `(..., 3)`.

    **Returns:** unit directions `(..., 3)` in world space.
    """
    u = _point(u, 2, "u", "a point of [0,1)^2")
    axis, one_minus_cos = _sphere_cone(center, radius, ref)
    local = _cone_local(u, one_minus_cos)
    t, b = _frame(axis)
    local, t, b, axis = jnp.broadcast_arrays(local, t, b, axis)
    return local[..., 0:1] * t + local[..., 1:2] * b + local[..., 2:3] * axis


def sphere_solid_angle_pdf(
    w: ArrayLike, center: ArrayLike, radius: ArrayLike, ref: ArrayLike
) -> jax.Array:
    r"""Solid-angle density of `sphere_solid_angle`: $1/(2\pi(1 - \cos\theta_{max}))$ for
    directions `w` inside the subtended cone (i.e. rays from `ref` that hit the
    sphere), 0 otherwise. `w` is normalised first.

    The cone test compares half-angle sines, $|w - \hat d|/2 = \sin(\theta/2)$
    against $\sin(\theta_{max}/2) = \sqrt{(1 - \cos\theta_{max})/2}$, with a
    slack of two ulps: a unit vector stored in float32 only pins its angle down
    to about $10^{-7}$ rad, which for a tiny light is a sizeable fraction of
    $\theta_{max}$, and the warp's own samples must never get a zero pdf.
    """
    w = _unit(w)
    axis, one_minus_cos = _sphere_cone(center, radius, ref)
    w = w / jnp.linalg.norm(w, axis=-1, keepdims=True)
    w, axis = jnp.broadcast_arrays(w, axis)
    diff = w - axis
    half_sin = 0.5 * jnp.sqrt(jnp.sum(diff * diff, axis=-1))
    half_sin, one_minus_cos = jnp.broadcast_arrays(half_sin, one_minus_cos)
    half_sin_max = jnp.sqrt(0.5 * one_minus_cos)
    slack = 2 * jnp.finfo(half_sin.dtype).eps
    inside = (half_sin <= half_sin_max + slack) | (one_minus_cos >= 2.0)
    return jnp.where(inside, _cone_pdf_value(one_minus_cos), 0.0)


def sphere_solid_angle_inverse(
    w: ArrayLike, center: ArrayLike, radius: ArrayLike, ref: ArrayLike
) -> jax.Array:
    """Inverse of `sphere_solid_angle` for directions inside the subtended cone."""
    w = _unit(w)
    axis, one_minus_cos = _sphere_cone(center, radius, ref)
    t, b = _frame(axis)
    w, t, b, axis = jnp.broadcast_arrays(w, t, b, axis)
    x = jnp.sum(w * t, axis=-1)
    y = jnp.sum(w * b, axis=-1)
    diff = w - axis
    one_minus_cos_w = 0.5 * jnp.sum(diff * diff, axis=-1)
    return _stack(one_minus_cos_w / one_minus_cos, _wrap_angle(jnp.arctan2(y, x)))


# ---------------------------------------------------------------------------
# triangle


def triangle(u: ArrayLike) -> jax.Array:
    r"""Uniform barycentrics $(b_0, b_1)$ on the reference triangle (pdf 2).

    The triangle $\{b_0, b_1 \ge 0,\ b_0 + b_1 \le 1\}$ has area $1/2$, so
    $p = 2$. The marginal of $b_0$ is $p(b_0) = 2(1 - b_0)$ with CDF
    $1 - (1 - b_0)^2$, and $b_1 \mid b_0$ is uniform on $[0, 1 - b_0]$.
    Inverting (with $1 - u_1 \sim u_1$): $b_0 = 1 - \sqrt{u_1}$,
    $b_1 = u_2 \sqrt{u_1}$ (PBRT-v3 `UniformSampleTriangle`). A point of a
    triangle $(p_0, p_1, p_2)$ is then $b_0 p_0 + b_1 p_1 + (1 - b_0 - b_1) p_2$,
    with area density $1/A$.

    **Arguments:** `u` of shape `(..., 2)`. **Returns:** `(..., 2)` barycentrics.
    """
    u = _point(u, 2, "u", "a point of [0,1)^2")
    s = jnp.sqrt(u[..., 0])
    return _stack(1.0 - s, u[..., 1] * s)


def triangle_pdf(b: ArrayLike) -> jax.Array:
    """Density of `triangle` w.r.t. area in the $(b_0, b_1)$ plane: 2 inside, 0 outside."""
    b = _point(b, 2, "b", "barycentrics (b0, b1)")
    b0, b1 = b[..., 0], b[..., 1]
    inside = (b0 >= 0) & (b1 >= 0) & (b0 + b1 <= 1)
    return jnp.where(inside, 2.0, 0.0).astype(b.dtype)


def triangle_inverse(b: ArrayLike) -> jax.Array:
    """Inverse of `triangle`: $u = ((1 - b_0)^2, b_1/(1 - b_0))$."""
    b = _point(b, 2, "b", "barycentrics (b0, b1)")
    s = 1.0 - b[..., 0]
    safe_s = jnp.where(s > 0, s, 1.0)
    return _stack(s * s, jnp.where(s > 0, b[..., 1] / safe_s, 0.0))
