r"""A map bent towards a corner where $f$ is singular (`"corner_qmc"` of `integrate(method="auto")`).

A point singularity where several faces meet, $f \sim \rho^{-a}$ with $\rho$ the distance to
the corner (the corner singularity $(\sum_j x_j)^{-a}$; a product $\prod_j x_j^{-a_j}$;
$(x_1 + x_2)^{-a}$, where the corner is an edge of the box), makes QMC's values $f$ a
power-law tail, and a VEGAS grid's too: its bins near the corner hold a density that is
constant there, and their marginals, bounded where $a$ is below the number of axes that meet,
show no power law on any one axis (`_edged_grid` bends the faces where they do).

`CornerMap` bends the cube itself: on each of the $k$ axes that meet at the corner,
$x_j = c_j \pm z_j^{p}$ with $z_j$ uniform, a density $q \propto \prod_j x_j^{1/p - 1}$
(distances to the corner's faces). Along a ray to the corner, $z_j \sim r$ on every such axis,
$f \sim r^{-ap}$ and $1/q \sim r^{k(p - 1)}$: $f/q$ is bounded where $p \ge k/(k - a)$. QMC
keeps its rate on it. On $(\sum_j x_j)^{-3/2}$ in 4-D (relative variance per evaluation of
16 nets, against plain QMC's 2.2e-2 and 4.9e-3): $p = 2$ 1.4e-5 at $2^{14}$ points and
4.0e-7 at $2^{17}$; $f/q$ at most 4.4x its mean on $2^{21}$ points (uniform: 184x). The
trained grid bent on its first bins (`EdgedGrid` forced to $p = 1.9$) did not help there:
1.7e-3 against the grid's own 1.2e-3 at $2^{14}$.

The corner and $p$ come from $f$ itself (`corner_probe`, `corner_probe_evaluations`): on
each axis, the face that most of QMC's `CORNER_VOTERS` largest early values lie nearer (a
product $\prod_j x_j^{-1/3}$ peaks where one factor does, its point anywhere on the other
axes), and $\log|f|$ along rays to it, $2^{-4} \dots 2^{-16}$ of the way from the box's
centre. The slope on the ray to the corner is $-a$; held at the centre on axis $j$, the ray
grows less by what axis $j$ carries ($a$ itself for $(\sum_j x_j)^{-a}$, $a_j$ for a
product). The axes that carry at least `CORNER_MIN_SHARE` meet at the corner, and
$p = k/(k - a)$ (on a product of equal powers, each factor's $1/(1 - a_j)$), raised by
`EDGE_OVERSHOOT` (as the faces' are: a density that falls faster than $f$ leaves $f/q$
bounded), at most `MAX_EDGE_POWER`. A power law is read only where the slopes of the ray's
near and far halves agree within `CORNER_LAW_SLACK`: a peak at a corner (Genz's corner
peak) levels off, its near slope 0.
"""
from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .._box import log_volume, to_box
from .._integrand import evaluate
from .._proposals._base import sum_last
from ._edged_grid import EDGE_MIN_POWER, EDGE_OVERSHOOT, MAX_EDGE_POWER, MAX_FACE_SPACING


__all__ = ["CornerMap", "bends_corner", "corner_probe", "corner_probe_evaluations"]

# The ray's points: 2^-4, 2^-6, ..., 2^-16 of the way from the box's centre to the corner.
_RAY = tuple(2.0 ** -k for k in range(4, 17, 2))
CORNER_LAW_SLACK = 0.1  # the most the slopes of the ray's near and far halves may differ
CORNER_MIN_SHARE = 0.05  # the least of the slope an axis carries to meet at the corner
CORNER_VOTERS = 16  # the largest values whose points choose the corner, each axis by a vote


def corner_probe_evaluations(d: int) -> int:
    """The evaluations of `corner_probe` in `d` dimensions: a ray, and one per axis."""
    return len(_RAY) * (d + 1)


class CornerMap(eqx.Module):
    r"""The unit cube bent towards a corner (see the module's docstring): on axis $j$,
    $x_j = lo_j + z^{p_j}$ (or $hi_j - z^{p_j}$ where `toward_hi`), $z$ the unit point's
    coordinate; $p_j = 1$ leaves the axis uniform."""

    lo: jax.Array
    hi: jax.Array
    toward_hi: jax.Array  # (d,) bool: the corner's face on each axis
    power: jax.Array  # (d,) p_j >= 1
    event_ndim = 1

    @property
    def dim(self) -> int:
        return self.lo.shape[0]

    @property
    def powered(self) -> jax.Array:
        """Whether any axis maps with a power other than 1 (as `EdgedGrid.powered`)."""
        return jnp.any(self.power != 1)

    def map(self, u):
        """`(x, log q(x))` on the box for unit points `u` `(n, d)`, as a grid's `map`."""
        z = jnp.maximum(u, jnp.finfo(u.dtype).tiny)
        log_z = jnp.log(z)
        distance = jnp.exp(self.power * log_z)
        x = to_box(jnp.where(self.toward_hi, 1 - distance, distance), self.lo, self.hi)
        # q = prod_j 1 / (p_j z_j^(p_j - 1)) on the unit cube.
        log_q = -sum_last(jnp.log(self.power) + (self.power - 1) * log_z)
        return x, log_q - log_volume(self.lo, self.hi)


@eqx.filter_jit
def corner_probe(f, batched, lo, hi, points, values):
    r"""`(CornerMap, whether f is singular at its corner)` from $f$ along rays to the corner
    that the points of `points` `(..., d)` (in the box, or a function of no arguments that
    makes them) with the largest `values` lie nearest, by a vote (see the module's docstring;
    `corner_probe_evaluations(d)` evaluations). A face is bent only where the box's
    coordinates resolve distances to it of `MAX_FACE_SPACING` of its width (in float32,
    only faces at 0: see `_edged_grid.edge_powers`)."""
    d = lo.shape[0]
    width = hi - lo
    x = jnp.reshape(points() if callable(points) else points, (-1, d))
    magnitude = jnp.sum(jnp.reshape(jnp.abs(values), (x.shape[0], -1)), axis=1)
    best = (x[jnp.argsort(-magnitude)[:CORNER_VOTERS]] - lo) / width
    toward_hi = jnp.mean(best > 0.5, axis=0) > 0.5  # (most of them on that half)
    corner = toward_hi.astype(lo.dtype)
    t = jnp.asarray(_RAY, lo.dtype)
    # Rays (d + 1, len(_RAY), d): to the corner, then to it with axis j held at the centre.
    ray = corner + t[:, None] * (0.5 - corner)
    held = jnp.where(jnp.eye(d, dtype=bool)[:, None, :], 0.5, ray[None])
    u = jnp.concatenate([ray[None], held])
    y = evaluate(f, jnp.reshape(lo + width * u, (-1, d)), batched)
    size = jnp.sqrt(jnp.sum(jnp.reshape(jnp.abs(y) ** 2, u.shape[:2] + (-1,)), axis=-1))
    log_f = jnp.log(size)  # (d + 1, len(_RAY)): the norm of f's components
    log_t = jnp.log(t)

    def slope(v, lt):
        centred = lt - jnp.mean(lt)
        return jnp.sum((v - jnp.mean(v, axis=-1, keepdims=True)) * centred, axis=-1) \
            / jnp.sum(centred**2)

    half = len(_RAY) // 2 + 1
    a = -slope(log_f, log_t)  # (d + 1,) the growth on each ray
    far, near = -slope(log_f[0, :half], log_t[:half]), -slope(log_f[0, -half:], log_t[-half:])
    carried = a[0] - a[1:]  # what each axis carries of it
    resolved = jnp.abs(jnp.spacing(jnp.where(toward_hi, hi, lo))) <= MAX_FACE_SPACING * width
    meets = (carried >= CORNER_MIN_SHARE) & resolved
    k = jnp.sum(meets).astype(lo.dtype)
    power = k / jnp.maximum(k - a[0], k / MAX_EDGE_POWER)
    law = jnp.all(jnp.isfinite(log_f)) & (jnp.abs(near - far) <= CORNER_LAW_SLACK)
    singular = law & (k > 0) & (power >= EDGE_MIN_POWER)
    power = jnp.where(meets & singular, jnp.minimum(EDGE_OVERSHOOT * power, MAX_EDGE_POWER), 1.0)
    return CornerMap(lo, hi, toward_hi, power), singular


@jax.jit
def bends_corner(corner: CornerMap, low, high) -> jax.Array:
    """Whether a grid bent with powers `low`, `high` at its faces (`_edged_grid.edge_powers`)
    is bent at every face that meets at `corner`."""
    bent = jnp.where(corner.toward_hi, high, low) > 1
    return jnp.all(bent | (corner.power == 1))
