r"""Infinite limits: each unbounded axis mapped onto a finite interval, fitted to the integrand.

An axis $(-\infty, \infty)$ is mapped from $t \in (-1, 1)$, an axis $[a, \infty)$ (or
$(-\infty, b]$) from $t \in (0, 1)$, by

$$x = c + \tfrac{s k}{2}\left[(1 - t)^{-1/k} - (1 + t)^{-1/k}\right], \qquad
x = a + s k \left[(1 - t)^{-1/k} - 1\right],$$

with Jacobians $\tfrac{s}{2}[(1-t)^{-1/k-1} + (1+t)^{-1/k-1}]$ and $s (1-t)^{-1/k-1}$:
the integral of $f$ over the unbounded box is that of $f(x(t))\,|x'(t)|$ over the finite
one. $k = 1$ is the rational map $x = c + s\,t/(1 - t^2)$ of vegas's and Cuba's tutorials;
as $k \to \infty$ the maps tend to the logistic and exponential quantiles. The density
$1/|x'|$ the map puts on $x$ has tails $\propto |x|^{-(k+1)}$ (a Student-t-like map with
$k$ degrees of freedom; a Lomax one on a half-line), so

- $f(x(t))\,|x'(t)|$ stays bounded where $|f|$ decays at least as $|x|^{-(k+1)}$: a map
  with lighter tails than $f$ gives unbounded values and, past that, infinite variance
  (Owen 2013, *Monte Carlo theory, methods and examples*, ch. 9, on importance sampling
  with tails lighter than the integrand's);
- the centre $c$ and scale $s$ set where the samples go (the transformed integrand is
  flattest when the map's quartiles are $|f|$'s).

`fit_maps` measures both from the integrand: two pilots of uniform points through the map
(the first a heavy-tailed default) give the weighted quartiles of $|f|$'s marginal on each
axis, so the map's quartiles (its median, on a half-line) are set to them; probes along
each unbounded axis and along the diagonal of all of them, out to $2^{20}$ scales, measure
the decay exponent $a$ of $|f|$ ($|f| \sim r^{-a}$, the slope of $\log|f|$ against
$\log r$). Along one axis the map is bounded for $k \le a - 1$; along the diagonal of $m$
unbounded axes, where $m$ Jacobians multiply, for $\sum_j (k_j + 1) \le a_\mathrm{diag}$.
`tail` is the largest $k$ both allow, between `MIN_TAIL` and `MAX_TAIL` (the rational
map); an integrand decaying faster than any power gets `MAX_TAIL`. Where no map can bound
$f\,|x'|$ (a decay slower than $|x|^{-1.5}$ along an axis), the diagnostics read the values'
power-law tail; and as the map reaches only some $10^{14}$ scales in float32 ($10^{32}$ in
float64: where $1 - t$ meets the dtype's resolution), the share of so slow a tail's mass
beyond it is estimated (`reach_loss`) and the estimate flagged where it exceeds the error bar.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._box import to_box
from ._compiled import per_integrand
from ._integrand import evaluate


FINITE, TWO_SIDED, ABOVE_LO, BELOW_HI = 0, 1, 2, 3  # an axis's kind
# The heaviest map tail (density ~ |x|^-1.5): bounds any f decaying as |x|^-1.5 or faster.
MIN_TAIL = 0.5
# The lightest, for f decaying as |x|^-2 or faster: the rational map x = c + s t/(1 - t^2).
# Lighter tails squeeze f's decay into the last bins of the VEGAS grid that adaptive
# methods train on top, where f/p then has a tail the diagnostics read as a power law.
MAX_TAIL = 1.0
# Tail probes at 2^8 ... 2^20 scales from the bulk: far enough for the asymptotic slope.
PROBE_OCTAVES = tuple(range(8, 21))
PILOT_ROUNDS = 2


def axis_kinds(lo, hi) -> tuple[int, ...] | None:
    r"""Each axis's kind (`FINITE`, `TWO_SIDED`, `ABOVE_LO` for $[a, \infty)$, `BELOW_HI` for
    $(-\infty, b]$) for the bounds as given (checked by `check_bounds`), or `None` when every
    axis is finite or a bound is traced: under `jit` an infinite limit must be a constant
    (a Python or NumPy value, or an array from outside), not an argument of the function."""
    try:
        lo_np, hi_np = (np.atleast_1d(np.asarray(b, dtype=float)) for b in (lo, hi))
    except (TypeError, ValueError, jax.errors.TracerArrayConversionError,
            jax.errors.ConcretizationTypeError):
        return None  # (bad bounds: `check_bounds` says why)
    below, above = np.isneginf(lo_np), np.isposinf(hi_np)
    if not (below.any() or above.any()):
        return None
    kinds = np.where(below & above, TWO_SIDED,
                     np.where(above, ABOVE_LO, np.where(below, BELOW_HI, FINITE)))
    return tuple(int(k) for k in kinds)


class AxisMaps(eqx.Module):
    r"""The maps of a box's axes from a finite box (`box`): $x(t)$ and $\log|\det x'(t)|$.

    **Fields:** `kinds` (static, per axis), `anchor` (the centre $c$ of a two-sided axis,
    the finite end of a half-line), `scale` ($s$) and `tail` ($k$), each of the bounds'
    shape; finite axes are the identity. `beyond_reach`: the share of the integral the
    map never samples, estimated from the measured decays (`reach_loss`).
    """

    kinds: tuple[int, ...] = eqx.field(static=True)
    anchor: jax.Array
    scale: jax.Array
    tail: jax.Array
    beyond_reach: jax.Array = eqx.field(default_factory=lambda: np.asarray(0.0))

    def _masks(self, shape):
        kinds = np.reshape(np.asarray(self.kinds), shape)
        return kinds == TWO_SIDED, kinds == ABOVE_LO, kinds == BELOW_HI, kinds == FINITE

    def box(self, lo: jax.Array, hi: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The finite box the maps start from: $(-1, 1)$ for two-sided axes, $(0, 1)$ for
        half-lines, finite axes unchanged."""
        two, _, _, finite = self._masks(lo.shape)
        return (jnp.where(finite, lo, jnp.where(two, -1.0, 0.0)).astype(lo.dtype),
                jnp.where(finite, hi, 1.0).astype(hi.dtype))

    def __call__(self, t: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Points `t` (shape `(..., *bounds' shape)`) mapped: `(x, log_jacobian)`, the latter
        summed over the axes (shape `(...)`)."""
        def rational(u):
            x, jac = self._rational(u)
            log_j = jnp.log(jac)
            return x, jnp.sum(log_j, axis=-1) if self.anchor.shape else log_j

        return jax.lax.cond(self.rational, rational, lambda u: self._powers(u), t)

    def with_jacobian(self, t: jax.Array) -> tuple[jax.Array, jax.Array]:
        """`(x, |det x'(t)|)`: as calling the maps, the Jacobian's product taken directly."""
        def rational(u):
            x, jac = self._rational(u)
            return x, jnp.prod(jac, axis=-1) if self.anchor.shape else jac

        def powers(u):
            x, log_j = self._powers(u)
            return x, jnp.exp(log_j)

        return jax.lax.cond(self.rational, rational, powers, t)

    @property
    def rational(self) -> jax.Array:
        """Whether every map is the rational one ($k = 1$ on every unbounded axis; finite axes
        hold 1): it needs no transcendental function, and maps points several times faster."""
        return jnp.all(self.tail == 1)

    def _rational(self, t):
        """`(x, x')` per axis for $k = 1$: $x = c + s\\,t/(1 - t^2)$,
        $x' = s\\,(1 + t^2)/(1 - t^2)^2$ on two-sided axes; $x = a \\pm s\\,t/(1 - t)$,
        $x' = s/(1 - t)^2$ on half-lines ($(1 - t)(1 + t)$ keeps $1 - t$ exact near the
        ends); finite axes unchanged, $x' = 1$."""
        two, above, below, finite = self._masks(self.anchor.shape)
        s, c = self.scale, self.anchor
        free = jnp.where(finite, 0.0, t)
        minus = 1 - free
        denominator = jnp.where(two, minus * (1 + free), minus)
        ratio = free / denominator
        x = jnp.where(two | above, c + s * ratio, jnp.where(below, c - s * ratio, t))
        jac = jnp.where(two, s * (1 + free * free), s) / (denominator * denominator)
        return x, jnp.where(finite, 1.0, jac)

    def _powers(self, t):
        two, above, below, finite = self._masks(self.anchor.shape)
        k, s, c = self.tail, self.scale, self.anchor
        # (1 -+ t)^(-1/k) - 1 as expm1 of logarithms: no cancellation near t = 0 or large k.
        up = -jnp.log1p(-jnp.where(finite, 0.0, t))  # -log(1 - t)
        down = -jnp.log1p(jnp.where(two, t, 0.0))  # -log(1 + t), two-sided axes only
        outward = k * jnp.expm1(up / k)
        x_two = c + 0.5 * s * (outward - k * jnp.expm1(down / k))
        x = jnp.where(two, x_two, jnp.where(above, c + s * outward, jnp.where(below, c - s * outward, t)))
        power = 1.0 + 1.0 / k
        log_two = jnp.log(0.5 * s) + jnp.logaddexp(power * up, power * down)
        log_j = jnp.where(two, log_two, jnp.where(finite, 0.0, jnp.log(s) + power * up))
        if self.anchor.shape:  # (d,) bounds: one Jacobian per point
            log_j = jnp.sum(log_j, axis=-1)
        return x, log_j


def unit_quantile(tail: jax.Array, two_sided: jax.Array) -> jax.Array:
    r"""$x(t)$ at the map's upper quartile ($t = 1/2$, two-sided; from the centre) or median
    ($t = 1/2$ on a half-line; from the end), for $c = 0$, $s = 1$."""
    k = tail
    upper_quartile = 0.5 * k * (jnp.expm1(math.log(2.0) / k) - jnp.expm1(-math.log(1.5) / k))
    median = k * jnp.expm1(math.log(2.0) / k)
    return jnp.where(two_sided, upper_quartile, median)


class MappedIntegrand(eqx.Module):
    """`f` on the finite box: $f(x(t))\\,|\\det x'(t)|$ (zero where `f` is, whatever the
    Jacobian). For a point, or a batch with `batched`."""

    f: Callable
    maps: AxisMaps
    batched: bool = eqx.field(static=True)

    def __call__(self, t: jax.Array) -> jax.Array:
        x, jac = self.maps.with_jacobian(t)
        fx = jnp.asarray(self.f(x))
        if not jnp.issubdtype(fx.dtype, jnp.floating):
            fx = fx.astype(jnp.result_type(float))
        lead = jac.ndim  # (1 for a batch, 0 for a point)
        jac = jnp.reshape(jac, jac.shape + (1,) * (fx.ndim - lead)).astype(fx.dtype)
        return jnp.where(fx == 0, jnp.zeros_like(fx), fx * jac)


class MappedLogDensity(eqx.Module):
    r"""$\log\pi(x(t)) + \log|\det x'(t)|$: a log density on the finite box."""

    log_density: Callable
    maps: AxisMaps

    def __call__(self, t: jax.Array) -> jax.Array:
        x, log_j = self.maps(t)
        return jnp.asarray(self.log_density(x)) + log_j.astype(x.dtype)


class ComposedWithMap(eqx.Module):
    """`g(x(t))`: a function of the original variables on the finite box."""

    g: Callable
    maps: AxisMaps

    def __call__(self, t: jax.Array) -> jax.Array:
        return self.g(self.maps(t)[0])


def map_pilot_size(budget: int) -> int:
    """Points in each of `fit_maps`' pilots for a run of `budget` evaluations: a 64th of it,
    between 128 and 1024 (the quartiles' relative error is then a few per cent)."""
    return int(min(max(budget // 64, 128), 1024))


def probe_count(kinds: tuple[int, ...], pilot: int) -> int:
    """The evaluations `fit_maps` spends: its pilots and its tail probes."""
    unbounded = [k for k in kinds if k != FINITE]
    directions = sum(2 if k == TWO_SIDED else 1 for k in unbounded) + 2
    return PILOT_ROUNDS * pilot + directions * len(PROBE_OCTAVES)


def fit_maps(key, f: Callable, lo: jax.Array, hi: jax.Array, *, kinds: tuple[int, ...],
             pilot: int, batched: bool, log_values: bool = False) -> AxisMaps:
    """Maps of the unbounded axes fitted to `f` (module docstring), on `probe_count(kinds,
    pilot)` evaluations of `f` (a log density with `log_values`)."""
    return per_integrand(_fit_maps)(key, f, lo, hi, kinds=kinds, pilot=pilot, batched=batched,
                                    log_values=log_values)


def map_expectation(key, g, log_density, lo, hi, *, kinds, n, minimum, batched):
    """`g` and `log_density` carried onto the finite box by maps fitted to the density, for
    `expectation` with `n` evaluations of which `minimum` must be left after the fit:
    `(g, log_density, lo, hi, evaluations spent)`."""
    pilot = map_pilot_size(n)
    probes = probe_count(kinds, pilot)
    if n - probes < minimum:
        raise ValueError(
            f"with infinite limits `expectation` spends {probes} evaluations fitting a map of "
            f"the infinite axes, and needs {minimum} more: `n` must be at least "
            f"{minimum + probes}, got {n}.")
    maps = jax.lax.stop_gradient(fit_maps(key, log_density, lo, hi, kinds=kinds, pilot=pilot,
                                          batched=batched, log_values=True))
    lo, hi = maps.box(lo, hi)
    return ComposedWithMap(g, maps), MappedLogDensity(log_density, maps), lo, hi, probes


def _fit_maps(key, f, lo, hi, *, kinds, pilot, batched, log_values):
    dtype = lo.dtype
    shape = lo.shape
    kind = np.reshape(np.asarray(kinds), shape)
    finite = kind == FINITE

    def log_abs(x):
        y = evaluate(f, x, batched)
        if log_values:
            return jnp.reshape(y, (x.shape[0],)).astype(dtype)
        y = jnp.reshape(jnp.abs(y), (x.shape[0], -1)).astype(dtype)
        return jnp.log(jnp.sum(y, axis=1))

    ones = jnp.ones(shape, dtype)
    # (Two-sided axes start centred at 0, half-lines at their finite end.)
    anchor = jnp.where(kind == ABOVE_LO, lo, jnp.where(kind == BELOW_HI, hi, 0.0))
    maps = AxisMaps(kinds, anchor.astype(dtype), ones, ones)
    keys = jax.random.split(key, PILOT_ROUNDS)
    quartiles = None
    for round_key in keys:
        t_lo, t_hi = maps.box(lo, hi)
        t = to_box(jax.random.uniform(round_key, (pilot,) + shape, dtype), t_lo, t_hi)
        x, log_j = maps(t)
        log_w = log_abs(x) + log_j
        log_w = jnp.where(jnp.isnan(log_w) | (log_w == jnp.inf), -jnp.inf, log_w)
        top = jnp.max(log_w)
        seen = jnp.isfinite(top)
        w = jnp.exp(log_w - jnp.where(seen, top, 0.0))
        found = _weighted_quantiles(jnp.reshape(x, (pilot, -1)), w, (0.25, 0.5, 0.75))
        found = jnp.reshape(found, (3,) + shape)
        quartiles = found if quartiles is None else jnp.where(seen, found, quartiles)
        maps = _matched(maps, quartiles, maps.tail, seen)

    base = jnp.where(finite, jnp.clip(quartiles[1], lo, hi), quartiles[1])
    tail, decay = _tails(log_abs, base, maps.scale, kinds, dtype)
    maps = _matched(maps, quartiles, tail, jnp.all(jnp.isfinite(quartiles)))
    return eqx.tree_at(lambda m: m.beyond_reach, maps, reach_loss(tail, decay, dtype))


def _matched(maps, quartiles, tail, ok):
    """`maps` with tail `tail`, and its centre and scale set so that its quartiles (two-sided)
    or its median (half-lines) are `quartiles`' (where `ok` and the result is sound)."""
    two, above, _, _ = maps._masks(maps.anchor.shape)
    q25, q50, q75 = quartiles
    spread = jnp.where(two, 0.5 * (q75 - q25), jnp.where(above, q50 - maps.anchor, maps.anchor - q50))
    scale = spread / unit_quantile(tail, two)
    good = ok & jnp.isfinite(scale) & (scale > 0)
    anchor = jnp.where(two & ok & jnp.isfinite(q50), q50, maps.anchor)
    return AxisMaps(maps.kinds, anchor.astype(maps.anchor.dtype),
                    jnp.where(good, scale, maps.scale).astype(maps.scale.dtype),
                    jnp.asarray(tail, maps.tail.dtype) * jnp.ones_like(maps.tail),
                    maps.beyond_reach)


def _weighted_quantiles(x: jax.Array, w: jax.Array, levels) -> jax.Array:
    """Quantiles at `levels` of each column of `x` (shape `(n, d)`) under weights `w`:
    shape `(len(levels), d)`; NaN where every weight is zero."""
    order = jnp.argsort(x, axis=0)
    xs = jnp.take_along_axis(x, order, axis=0)
    cumulative = jnp.cumsum(w[order], axis=0)
    total = cumulative[-1]
    rows = []
    for level in levels:
        index = jax.vmap(jnp.searchsorted, in_axes=(1, 0))(cumulative, level * total)
        index = jnp.clip(index, 0, x.shape[0] - 1)
        rows.append(jnp.where(total > 0, xs[index, jnp.arange(x.shape[1])], jnp.nan))
    return jnp.stack(rows)


def _tails(log_abs, base, scale, kinds, dtype):
    """Each axis's `tail` $k$: the largest both its own decay exponent and the diagonal's
    allow (module docstring), from `log_abs` at `PROBE_OCTAVES` scales out of `base`; and
    each axis's decay exponent (the slower of its own and its share of the diagonal's)."""
    shape, d = base.shape, len(kinds)
    kind = np.asarray(kinds)
    unbounded = kind != FINITE
    outward = np.where(kind == BELOW_HI, -1.0, 1.0)
    # Directions: +/- each two-sided axis, outward along each half-line, the diagonal both ways.
    directions, owners = [], []
    for j in np.flatnonzero(unbounded):
        directions.append(np.eye(d)[j] * outward[j])
        owners.append(j)
        if kind[j] == TWO_SIDED:
            directions.append(-np.eye(d)[j])
            owners.append(j)
    for sign in (1.0, -1.0):
        directions.append(np.where(unbounded, np.where(kind == TWO_SIDED, sign, outward), 0.0))
        owners.append(-1)
    directions, owners = np.stack(directions), np.asarray(owners)
    radii = np.asarray([2.0 ** o for o in PROBE_OCTAVES])
    steps = jnp.asarray(radii[None, :, None] * directions[:, None, :], dtype)  # (m, r, d)
    points = jnp.reshape(base, (-1,)) + steps * jnp.reshape(scale, (-1,))
    values = log_abs(jnp.reshape(points, (-1,) + shape)).reshape(points.shape[:2])
    slopes = -(values[:, 1:] - values[:, :-1]) / math.log(2.0)
    # A pair whose far value is zero decays faster than any power; a NaN says nothing.
    slopes = jnp.where(jnp.isnan(slopes) | (values[:, :-1] == -jnp.inf), jnp.inf, slopes)
    decay = jnp.min(slopes, axis=1)  # (m,)
    mine = owners[:, None] == np.arange(d)[None, :]
    along = jnp.min(jnp.where(mine, decay[:, None], jnp.inf), axis=0)
    diagonal = jnp.min(jnp.where(owners == -1, decay, jnp.inf))
    decay = jnp.minimum(along, diagonal / int(unbounded.sum()))
    tail = jnp.clip(decay - 1.0, MIN_TAIL, MAX_TAIL)
    decay = jnp.where(unbounded, decay, jnp.inf)
    return (jnp.reshape(jnp.where(unbounded, tail, 1.0), shape).astype(dtype),
            jnp.reshape(decay, shape).astype(dtype))


def reach_loss(tail, decay, dtype) -> jax.Array:
    r"""The share of the integral beyond the maps' reach: the largest over the axes of
    $(R/s)^{1-a}$, the mass of a tail $|f| \propto |x|^{-a}$ (`decay`) beyond $R$ relative to
    its mass from one scale $s$ out, with $R/s = k\,\epsilon^{-1/k}$ the farthest a map of
    tail $k$ reaches from $1 - t = \epsilon$, the dtype's resolution near 1 ($2^{-24}$ in
    float32: some $10^{14}$ scales for $k = 1/2$; $2^{-53}$ in float64). Negligible for any
    tail the map bounds; a sizeable share, a bias, for one decaying slower than $|x|^{-1.5}$."""
    eps = float(np.finfo(dtype).epsneg)
    log_reach = jnp.log(tail) - jnp.log(eps) / tail
    loss = jnp.exp(jnp.minimum(1.0 - decay, 0.0) * log_reach)
    return jnp.max(jnp.where(jnp.isfinite(decay), loss, 0.0)).astype(dtype)
