r"""The VEGAS rules for a `Grid`: grid refinement (Lepage 1978) and VEGAS+ stratification (Lepage 2021).

`Vegas` draws i.i.d. points through the grid's map, estimates the integral,
and refines the grid on the weights $(f/p)^2$ (`Grid.refine_bins`). `VegasPlus`
also cuts the unit cube of the map into hypercubes and spreads each round's
points over them: a quarter evenly (at least two per cube), the rest
$\propto \sigma_h^\beta$ with $\sigma_h$ the previous round's standard
deviation of $f/p$ in cube $h$ (adaptive stratified sampling, §4.2).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _random
from .._integrand import ratio
from .._points._common import open_unit
from .._stats import estimate_iid, slot_of_sample, stratified_estimate
from ..proposals import Grid
from ._rule import AbstractAdaptation, Integrand, Samples


# Share of each round's samples spread evenly over the hypercubes (at least two per
# cube); the rest go where sigma_h is large. vegas's default `neval_frac` is the
# adaptive share, 0.75.
_UNIFORM_SHARE = 0.25
# Hypercube indices are turned into corners in float arithmetic (`_corners`): exact below this.
MAX_STRATA = 2**22


def _sq_norm(y: jax.Array) -> jax.Array:
    return jnp.sum(jnp.reshape(y, (y.shape[0], -1)) ** 2, axis=-1)


def _unit(y: jax.Array) -> jax.Array:
    """A power of two to divide a round's values by before they are squared: the one at or
    just above the largest $|y|$ where that is beyond $2^{e/3}$ ($4 \\times 10^{12}$ in
    float32, $4 \\times 10^{102}$ in float64, $2^e$ the dtype's range: sums of many
    squares would overflow) or below $2^{-e/2}$ ($5 \\times 10^{-20}$, $7 \\times
    10^{-155}$: every square underflows); 1 otherwise.

    In float32 only values from $10^{-19}$ to $10^{19}$ have squares in range: beyond,
    the grid would refine on squares overflowed to inf or underflowed to zero, blind to
    where $f$ is largest. Dividing by a power of two rounds nothing but values it makes
    subnormal or lifts out of it; in range, where the unit is 1, results are bit for bit
    as without it. (Lifting a far tail out of the subnormals changes what a grid grazing
    a missed peak learns: rounds that saw only such a tail count more of it, and
    `adapt`'s rounds can then disagree.)"""
    largest = jnp.max(jnp.abs(jax.lax.stop_gradient(y)))
    _, exponent = jnp.frexp(largest)
    reach = jnp.finfo(y.dtype).maxexp
    in_range = (exponent <= reach // 3) & (exponent >= -(reach // 2))
    return jnp.ldexp(jnp.ones((), y.dtype), jnp.where(in_range, 0, exponent))


def _in_units(est, unit):
    """`est` of values divided by `unit`, in the values' own units (the variance may then leave
    the dtype's range, which `stats.unreliable` flags)."""
    return eqx.tree_at(lambda e: (e.mean, e.variance), est,
                       (est.mean * unit, est.variance * unit * unit))


def _check_grid(proposal, rule: str) -> None:
    if not isinstance(proposal, Grid):
        raise ValueError(f"{rule} adapts a Grid proposal, got {type(proposal).__name__}.")


def _round_uniforms(key, index, n: int, grid: Grid) -> jax.Array:
    return _random.uniform(jax.random.fold_in(key, index), (n, grid.dim), grid.lo.dtype)


def _points(grid: Grid, x: jax.Array) -> jax.Array:
    return x[:, 0] if grid.event_ndim == 0 else x


class VegasState(eqx.Module):
    """The grid, the next round's points on the unit cube and the grid's lookup table.

    The next round's points and the refined grid's table are made at the end of
    a round and carried: loop-carried arrays are stored, so neither the random
    generator nor the table's softmax is re-run inside the map's gathers, which
    XLA on the CPU would otherwise fuse them into (a scalar loop).
    """

    grid: Grid
    u: jax.Array
    table: tuple[jax.Array, jax.Array, jax.Array]


class Vegas(AbstractAdaptation):
    r"""VEGAS grid refinement: i.i.d. points through the grid, refined on $(f/p)^2$ with damping `alpha`."""

    alpha: float = 0.5

    def check(self, proposal, n):
        _check_grid(proposal, "Vegas")

    def init(self, key, proposal, n):
        return VegasState(proposal, _round_uniforms(key, 0, n, proposal), proposal.lookup_table())

    def step(self, key, index, state, integrand: Integrand):
        grid, n = state.grid, state.u.shape[0]
        x, log_p, bins = grid.map_with_bins(state.u, state.table)
        x = _points(grid, x)
        fx = integrand(x)
        y, bad = ratio(fx, jnp.exp(log_p))
        est = estimate_iid(y, bad)
        grid = grid.refine_bins(bins, _sq_norm(y / _unit(y)) / n, alpha=self.alpha)
        samples = Samples(x, fx, log_p, jnp.full((n,), 1.0 / n, log_p.dtype))
        u = _round_uniforms(key, index + 1, n, grid)
        return VegasState(grid, u, grid.lookup_table()), est, samples

    def proposal(self, state):
        return state.grid


def strata_per_axis(d: int, n: int, max_strata: int) -> tuple[int, ...]:
    r"""Strata per axis for VEGAS+, as vegas chooses them.

    $n_s = \lfloor (n_0/2)^{1/d} \rfloor$ with $n_0$ the evenly spread share of
    the `n` samples, so each hypercube gets about two of those; then as many axes
    as still fit get $n_s + 1$ strata. At most `max_strata` hypercubes.
    """
    n0 = _UNIFORM_SHARE * n
    ns = max(1, int((n0 / 2) ** (1.0 / d) + 1e-9))
    while ns > 1 and ns**d > max_strata:
        ns -= 1
    strata = [ns] * d
    for j in range(d):
        bigger = strata.copy()
        bigger[j] += 1
        if 2 * math.prod(bigger) > n0 or math.prod(bigger) > max_strata:
            break
        strata = bigger
    return tuple(strata)


def allocate_to_hypercubes(sigma: jax.Array, n: int, beta) -> jax.Array:
    r"""Samples per hypercube: an even floor $m_0 \ge 2$ each plus the rest $\propto \sigma_h^\beta$.

    The proportional shares are rounded systematically (the rounded cumulative
    sum is differenced), so the counts sum to `n` exactly and each is within one
    of its share: no sort, which matters at thousands of hypercubes.
    """
    h = sigma.shape[0]
    m0 = max(2, int(_UNIFORM_SHARE * n / h))
    spare = n - m0 * h
    s = jnp.where(jnp.isfinite(sigma) & (sigma > 0), sigma, 0.0) ** beta
    total = jnp.sum(s)
    share = jnp.where(total > 0, s / jnp.where(total > 0, total, 1.0), 1.0 / h)
    cum = jnp.minimum(jnp.floor(jnp.cumsum(share) * spare + 0.5), spare).astype(jnp.int32)
    # A float cumsum summed as a tree (as XLA does on the CPU) can step down by a rounding
    # error; a running maximum restores monotone counts, so no cube drops below m0.
    cum = jax.lax.cummax(cum).at[-1].set(spare)
    return m0 + jnp.diff(cum, prepend=0)


def hypercube_corners(cube: jax.Array, strata: tuple[int, ...], dtype) -> jax.Array:
    """Lower corner (in strata units) of each hypercube, `(n,) -> (n, d)`, row-major order.

    Float arithmetic, exact for fewer than 2^22 hypercubes: `jnp.unravel_index`'s
    integer divisions run as a scalar loop on the CPU.
    """
    dtype = jnp.promote_types(dtype, jnp.float32)
    strides = np.array([math.prod(strata[j + 1 :]) for j in range(len(strata))], dtype)
    c = cube.astype(dtype)[:, None] + 0.5
    q = jnp.floor(c / strides)  # cube // stride, per axis
    sizes = np.asarray(strata, dtype)
    return q - sizes * jnp.floor((q + 0.5) / sizes)  # ... % strata


class StratifiedDraw(eqx.Module):
    """One VEGAS+ round's points on the unit cube, laid out hypercube by hypercube."""

    u: jax.Array  # (n, d) points
    cube: jax.Array  # (n,) hypercube of each point, non-decreasing
    counts: jax.Array  # (H,) points per hypercube


def stratified_unit_points(raw: jax.Array, counts: jax.Array, strata: tuple[int, ...]) -> StratifiedDraw:
    """Jitter uniforms `raw` `(n, d)` into the hypercubes of the unit cube, `counts[h]` in cube `h`.

    The cubes are the `prod(strata)` cells of a grid with `strata[j]` cells along
    axis $j$ (row-major order); the points come laid out cube by cube. They lie
    in the open cube: $(c + r)/s$ rounds to 1 in the last cube for $r$ near 1.
    """
    n = raw.shape[0]
    cube = slot_of_sample(counts, n)
    corner = hypercube_corners(cube, strata, raw.dtype)
    u = open_unit(((corner + raw) / np.asarray(strata, corner.dtype)).astype(raw.dtype))
    return StratifiedDraw(u, cube, counts)


class VegasPlusState(eqx.Module):
    """The grid, the next round's stratified points, the grid's lookup table (see
    `VegasState`) and whether the grid is refined at `VegasPlus.coarse_bins`."""

    grid: Grid
    draw: StratifiedDraw
    table: tuple[jax.Array, jax.Array, jax.Array]
    coarse: jax.Array


class VegasPlus(AbstractAdaptation):
    r"""VEGAS+: VEGAS refinement plus adaptive stratified sampling of the map's unit cube.

    The cube is cut into `prod(strata)` hypercubes $h$ of volume $v = 1/H$
    (`strata_per_axis`: about $n/8$ of them, at most `max_strata`); cube $h$
    gets $n_h$ samples (`allocate_to_hypercubes`, exponent `beta`; 0 gives
    uniform allocation), and $\hat I = v \sum_h \bar y_h$, $\hat V = v^2 \sum_h
    s_h^2 / n_h$ with $y = f/p$ (stratified sampling, §4.2). The grid is refined
    with damping `alpha` on $(f/p)^2$ weighted by each sample's volume $v/n_h$.
    With `diagnostics=False` a round's `Estimate` skips the search for its
    largest values $|y|$: no Pareto $\hat k$ (NaN) and no i.i.d. bound on a
    power-law tail (`stats.stratified_estimate`), which saves much of a small round's
    time; for rounds whose error bars are not reported.

    With `coarse_bins` $M$ (a divisor of the grid's bins) and `coarse` true, the
    grid is refined as a grid of $M$ bins held in its own (`Grid.refine_bins`).
    `coarse` may be traced: a grid refined either way keeps its shape, so one
    compiled program serves both, and the state carries the choice from `init`
    on (rounds that continue from a state keep it).
    """

    alpha: float = 0.5
    beta: float = 0.75
    max_strata: int = eqx.field(static=True, default=2**16)
    diagnostics: bool = eqx.field(static=True, default=True)
    coarse_bins: int | None = eqx.field(static=True, default=None)
    coarse: bool | jax.Array = False

    def check(self, proposal, n):
        _check_grid(proposal, "VegasPlus")
        if self.max_strata > MAX_STRATA:
            raise ValueError(f"`max_strata` must be at most 2**22, got {self.max_strata}.")
        if self.coarse_bins is not None and (
            not 1 <= self.coarse_bins <= proposal.bins or proposal.bins % self.coarse_bins
        ):
            raise ValueError(
                f"`coarse_bins` must divide the grid's {proposal.bins} bins, got {self.coarse_bins}."
            )

    def _stratified_draw(self, key, index, sigma, n, grid) -> StratifiedDraw:
        strata = strata_per_axis(grid.dim, n, self.max_strata)
        counts = allocate_to_hypercubes(sigma, n, self.beta)
        return stratified_unit_points(_round_uniforms(key, index, n, grid), counts, strata)

    def init(self, key, proposal, n):
        h = math.prod(strata_per_axis(proposal.dim, n, self.max_strata))
        sigma0 = jnp.ones((h,), proposal.lo.dtype)
        draw = self._stratified_draw(key, 0, sigma0, n, proposal)
        return VegasPlusState(proposal, draw, proposal.lookup_table(), jnp.asarray(self.coarse, bool))

    def step(self, key, index, state, integrand: Integrand):
        x, points = self.propose(state)
        return self.update(key, index, state, integrand(x), points)

    def propose(self, state):
        """The round's points, `(x as the integrand takes them, (x, log q(x), their bins))`:
        `step` is `update` after the integrand at `propose`'s points (split so that a loop of
        rounds run from Python compiles only the integrand's values for each integrand)."""
        x, log_p, bins = state.grid.map_with_bins(state.draw.u, state.table)
        return _points(state.grid, x), (x, log_p, bins)

    def update(self, key, index, state, fx, points):
        """The round's estimate from the integrand's values `fx` at `propose`'s points, and
        the state after it: `(state, Estimate, Samples)`, as `step`."""
        grid, draw = state.grid, state.draw
        x, log_p, bins = points
        x = _points(grid, x)
        h = draw.counts.shape[0]
        n = draw.u.shape[0]
        y, bad = ratio(fx, jnp.exp(log_p))
        vol = 1.0 / h
        # In units of the round's largest value (`_unit`): the allocation and the refinement
        # need only relative figures.
        unit = _unit(y)
        scaled = y / unit
        est, var_h = stratified_estimate(
            scaled, draw.cube, draw.counts, vol, jnp.sum(bad, dtype=jnp.int32), self.diagnostics
        )
        est = _in_units(est, unit)
        sigma = jnp.sqrt(jnp.sum(jnp.reshape(var_h, (h, -1)), axis=-1))
        # Each sample stands for volume v / n_h of the unit cube: each bin's mean of (f/p)^2,
        # weighted so, whatever the allocation (a ratio estimate, `Grid.refine_bins`).
        weight = vol / draw.counts.astype(y.dtype)[draw.cube]
        grid = grid.refine_bins(bins, weight * _sq_norm(scaled), alpha=self.alpha,
                                coarse_bins=self.coarse_bins, coarse=state.coarse,
                                point_weights=weight)
        samples = Samples(x, fx, log_p, weight)
        next_draw = self._stratified_draw(key, index + 1, sigma, n, grid)
        return VegasPlusState(grid, next_draw, grid.lookup_table(), state.coarse), est, samples

    def proposal(self, state):
        return state.grid
