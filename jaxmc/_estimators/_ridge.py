r"""A density along one direction, for integrands that vary along it alone (`"ridge_qmc"`).

A *ridge function* $f(x) = g(w \cdot x)$ (a resonance in $s = w \cdot x$ off the axes, a
corner singularity in $\sum_j x_j$, Genz's corner peak) is a peak along a line that no
product of axis densities follows: a VEGAS grid puts its mass on every combination of
the axes' bins near the ridge, and QMC's nets see the ridge as plain Monte Carlo would
(measured on an oblique resonance of width 0.01 in 4-D: variance times points ~10 from
$2^{10}$ to $2^{17}$ points per net, no better than plain Monte Carlo).

`RidgeMap` samples the unit cube with density $\propto h(w \cdot u)$ *conditionally*: with
$i$ the axis along which $w$ is largest ($w_i > 0$) and $c = \sum_{j \ne i} w_j u_j$, the
other coordinates are uniform and $s = w \cdot u$ runs over $I = [c, c + w_i]$, drawn from
the one-dimensional density $h$ restricted to $I$ (inverse CDF, $H$ its CDF), and
$u_i = (s - c)/w_i$. The density is

$$q(u) = \frac{w_i\,h(s)}{H(c + w_i) - H(c)},$$

normalised on the cube for any $h$ (integrate over $u_i$, then over the rest). For
$f = g(w \cdot u) \ge 0$ and $h \propto g$, $f/q = \int_0^1 f\,du_i$: the integral over one
axis is done exactly, and what is left is smooth in the others, where QMC's nets keep
their rate. $h$ is $|g|$ itself, read on the cube's diagonal, where $s$ runs over its whole
range (`profiled_ridge`), piecewise constant on equal steps in $s$, with a share spread
evenly (`RIDGE_DEFENSIVE`) so that $f/q$ stays bounded where $|g|$ varies within a step.
On the 3-D resonance of the tests (width 0.01) plain MC through it has 80x less variance
than on uniform points and $f/q$ no power-law tail (Pareto $\hat k < 0$).

The direction comes from the integrand's gradients (`ridge_direction`): those of a ridge
function are all parallel to $w$, so the matrix $\sum_k \hat g_k \hat g_k^\top$ of the unit
gradients at the QMC pilot's largest values has rank one; its leading eigenvector is $w$.
How `"auto"` weighs it against the other candidates: `_pilot_ridge`.
"""
from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .._integrand import evaluate
from ._plan import QMC_REPLICAS


RIDGE_PROBES = 16  # the QMC pilot's largest values at which the gradients are taken
# The gradients' second eigenvalue (of the first's) below which they are taken as parallel:
# 1e-30-1e-16 on exact ridges, 1e-2 and above elsewhere in the `auto` suite.
RIDGE_RANK = 1e-6
RIDGE_STEP, RIDGE_FLAT = 0.1, 1e-3  # a step across w (unit cube) and f's relative change
PROBE_EVALUATIONS = 2 * RIDGE_PROBES  # each probe with its gradient, and a step across
RIDGE_DEFENSIVE = 0.05  # the share of h spread evenly over the range of s
# The cost (relative variance per evaluation times relative time) of QMC's early look, and of
# the pilot's winner, below which no ridge is sought: the winners' were at most 0.2 on the
# ridge functions of the `auto` suite a ridge did not serve (Genz's corner peaks, (sum
# x)^-3/2, 4 keys at 1e5 and 3 at 1e6), 5-30 on the oblique resonances.
RIDGE_MIN_COST = 0.5
# (`jnp.searchsorted`'s unrolled binary search, for the guide table, built once a profile:
# 2x faster than its default on the CPU, 40-60x faster than sorting or comparing all.)
_SEARCH = "scan_unrolled"
_GUIDE, _GUIDED_SEARCH = 8, 3  # (5 halvings with one guide level a step: 1.6x the time)


class RidgeMap(eqx.Module):
    """The conditional ridge density on the box `[lo, hi]` (see the module's docstring), its
    profile $h$ piecewise constant on equal steps over the range of $s$."""

    lo: jax.Array
    hi: jax.Array
    direction: jax.Array  # w, unit, on the unit cube's coordinates, w[axis] > 0
    start: jax.Array  # the least s on the cube
    step: jax.Array  # the width of h's steps
    levels: jax.Array  # (steps + 1,) H at the steps' edges, 0 to 1
    guide: jax.Array  # (8 steps + 1,) the step holding each level g / (8 steps)
    axis: int = eqx.field(static=True)
    event_ndim = 1

    @property
    def dim(self) -> int:
        return self.lo.shape[0]

    def unit_map(self, u):
        """`(points on the unit cube, their density q, their s)` for `u` `(n, d)`."""
        w, i, levels = self.direction, self.axis, self.levels
        c = u @ w - u[:, i] * w[i]
        below, above = (self._cdf(c + t * w[i]) for t in (0.0, 1.0))
        t = below + u[:, i] * (above - below)
        j = self._step_of(t)
        mass_j = levels[j + 1] - levels[j]
        s = self.start + self.step * (j + (t - levels[j]) / mass_j)
        # (A concatenation, not a `where` or a scatter, into which XLA fused the search and
        # ran it once per coordinate: 1.5-2x the time in 12-D.)
        along = jnp.clip((s - c) / w[i], 0.0, 1.0)[:, None]
        x = jnp.concatenate([u[:, :i], along, u[:, i + 1:]], axis=1)
        mass = jnp.maximum(above - below, jnp.finfo(u.dtype).tiny)
        return x, w[i] * (mass_j / self.step) / mass, s

    def map(self, u):
        """`(x, log q(x))` on the box for unit points `u` `(n, d)`, as a grid's `map`."""
        x, q, _ = self.unit_map(u)
        width = self.hi - self.lo
        return self.lo + width * x, jnp.log(q) - jnp.sum(jnp.log(width))

    def _step_of(self, t):
        r"""The step of $H^{-1}(t)$: between the guide's steps for the levels around $t$
        (Chen and Asau's guide table, `_GUIDE` levels a step), a binary search of
        `_GUIDED_SEARCH` halvings. Every one of the $m$ steps holds at least
        $\epsilon/m$ of the mass (`RIDGE_DEFENSIVE`), so at most $1/(8\epsilon) + 2 = 4.5$
        lie between two guide levels ($2^3 = 8$)."""
        last = self.levels.shape[0] - 2
        cells = self.guide.shape[0] - 1
        g = jnp.clip(jnp.floor(t * cells).astype(jnp.int32), 0, cells - 1)
        low, high = self.guide[g], self.guide[g + 1]
        for _ in range(_GUIDED_SEARCH):
            middle = (low + high + 1) // 2
            below = self.levels[middle] <= t
            low, high = jnp.where(below, middle, low), jnp.where(below, high, middle - 1)
        return jnp.clip(low, 0, last)

    def _cdf(self, s):
        """$H(s)$, clamped to the range of $s$."""
        last = self.levels.shape[0] - 2
        position = jnp.clip((s - self.start) / self.step, 0.0, last + 1.0)
        j = jnp.minimum(jnp.floor(position).astype(jnp.int32), last)
        return self.levels[j] + (position - j) * (self.levels[j + 1] - self.levels[j])


@eqx.filter_jit
def ridge_direction(f, batched, lo, hi, points, values):
    """`(w, whether f looks like a ridge function along it, w's largest component's axis)`
    from the gradients of $f$ at the `RIDGE_PROBES` of `points` `(..., d)` (in the box, or a
    function of no arguments that makes them) with the largest `values`:
    $w$ the leading eigenvector of the sum of the unit gradients' outer products (on the unit
    cube's coordinates); a ridge where the second eigenvalue is below `RIDGE_RANK` times it,
    at least two gradients were finite and nonzero, and $f$ keeps its value, within
    `RIDGE_FLAT` of it, a step across $w$ away from each probe (a step `RIDGE_STEP` long, or
    half the way to the box's edge: Genz's discontinuous integrand has parallel gradients
    where it is not zero, and its edges cut across them)."""
    width = hi - lo
    x = jnp.reshape(points() if callable(points) else points, (-1, lo.shape[0]))
    magnitude = jnp.sum(jnp.reshape(jnp.abs(values), (x.shape[0], -1)), axis=1)
    probes = x[jnp.argsort(-magnitude)[:RIDGE_PROBES]]

    def value(p):
        return jnp.sum(jnp.real(evaluate(f, p[None], batched)[0]))

    values_at, g = jax.vmap(jax.value_and_grad(value))(probes)
    g = g * width
    norm = jnp.linalg.norm(g, axis=1, keepdims=True)
    usable = jnp.all(jnp.isfinite(g), axis=1, keepdims=True) & (norm > 0)
    unit = jnp.where(usable, g / jnp.where(usable, norm, 1.0), 0.0)
    eigenvalues, vectors = jnp.linalg.eigh(unit.T @ unit)
    w = vectors[:, -1]
    # A step across w from each probe (fixed directions: the choice stays a function of
    # the key), as long as the box allows.
    across = jax.random.normal(jax.random.key(0), probes.shape, probes.dtype)
    across = across - (across @ w)[:, None] * w
    across = across / jnp.maximum(jnp.linalg.norm(across, axis=1, keepdims=True), 1e-30)
    u = (probes - lo) / width
    room = jnp.min(jnp.where(across > 0, (1 - u) / jnp.where(across > 0, across, 1.0),
                             jnp.where(across < 0, -u / jnp.where(across < 0, across, -1.0),
                                       jnp.inf)), axis=1, keepdims=True)
    stepped = lo + width * (u + jnp.minimum(RIDGE_STEP, room / 2) * across)
    moved = jax.vmap(value)(stepped)
    flat = jnp.abs(moved - values_at) <= RIDGE_FLAT * jnp.abs(values_at)
    ridge = (jnp.sum(usable) >= 2) & (eigenvalues[-2] <= RIDGE_RANK * eigenvalues[-1]) \
        & jnp.all(flat | ~usable[:, 0])
    return w, ridge, jnp.argmax(jnp.abs(w))


def ridge_table_size(budget: int) -> int:
    """The profile's steps in $s$ (each read once): a power of two near `budget / 24`,
    1024 to 8192 (4% of the budget at 1e5, under 1% at 1e6; 4096 steps over the 4-D
    resonance's range of $s$ are 0.05 of its width)."""
    share = max(budget // 24, 1)
    return min(max(1 << (share.bit_length() - 1), 1024), 8192)


def ridge_evaluations(budget: int, per_replica: int) -> int:
    """The integrand evaluations of a ridge's profile (`ridge_table_size + 1` values) and of
    `QMC_REPLICAS` nets of `per_replica` points through it."""
    return ridge_table_size(budget) + 1 + per_replica * QMC_REPLICAS


@eqx.filter_jit
def profiled_ridge(lo, hi, direction, axis, *, f, batched, steps):
    r"""The `RidgeMap` along `direction` (its largest component at `axis`) whose profile is
    $|g|$ itself, read on `steps` equal steps of $s$ (the mean of its values at each step's
    two ends; the RMS of an array's components), with `RIDGE_DEFENSIVE` of it spread evenly.

    $g(s) = f(x)$ at any $x$ of the cube with $w \cdot x = s$ (`ridge_direction` checked
    $f$ is a ridge function): on the cube's diagonal from the corner where $s$ is least
    to the opposite one, $s$ runs over its whole range, linearly."""
    w = direction * jnp.sign(direction[axis])
    s_lo, s_hi = jnp.sum(jnp.minimum(w, 0)), jnp.sum(jnp.maximum(w, 0))
    fraction = jnp.linspace(0.0, 1.0, steps + 1, dtype=lo.dtype)
    least = (w < 0).astype(lo.dtype)  # the corner where s is least
    diagonal = least + fraction[:, None] * (1 - 2 * least)
    values = evaluate(f, lo + (hi - lo) * diagonal, batched)
    g = jnp.sqrt(jnp.sum(jnp.reshape(jnp.abs(values) ** 2, (steps + 1, -1)), axis=1))
    g = jnp.where(jnp.isfinite(g), g, 0.0)
    mass = 0.5 * (g[1:] + g[:-1])
    total = jnp.sum(mass)
    share = jnp.where(total > 0, mass / jnp.where(total > 0, total, 1.0), 1.0 / steps)
    share = (1 - RIDGE_DEFENSIVE) * share + RIDGE_DEFENSIVE / steps
    levels = jnp.concatenate([jnp.zeros((1,), lo.dtype), jnp.cumsum(share)])
    levels = (levels / levels[-1]).at[-1].set(1.0)
    at = jnp.linspace(0.0, 1.0, _GUIDE * steps + 1, dtype=lo.dtype)
    guide = jnp.searchsorted(levels, at, side="right", method=_SEARCH) - 1
    guide = jnp.clip(guide, 0, steps - 1).astype(jnp.int32)
    return RidgeMap(lo, hi, w, s_lo, (s_hi - s_lo) / steps, levels, guide, axis)


def room_for_a_ridge(cost, clear_win=False) -> jax.Array:
    """Whether a pilot's figures leave room for a ridge: no clear win for QMC, and a `cost`
    (QMC's, or the winner's) of at least `RIDGE_MIN_COST`."""
    return (cost >= RIDGE_MIN_COST) & ~jnp.asarray(clear_win)
