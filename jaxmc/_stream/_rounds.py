r"""VEGAS+ rounds: a grid trained, then refined as it is used (`jaxmc.methods.Adaptive`,
and `auto`'s grid stage).

Three stages of VEGAS+ rounds (`jaxmc.fit.VegasPlus`) of one size, `adaptive_block` (but
see 2):

1. **Training**: `training_rounds` rounds (at most a quarter of the budget)
   adapt the grid from uniform; their estimates are discarded.
2. **Refining**: the rest of a fixed budget (with a tolerance, up to
   `MAX_REFINE_ROUNDS` rounds) goes to rounds that each estimate the integral
   and go on refining the grid and the allocation for the next, as vegas adapts
   through the iterations it reports. Their estimates are averaged with
   weights growing with the round, fixed in advance, and the error bar is
   their scatter (`average_rounds`). Refining fixes what a grid frozen after
   a short training still gets wrong, and beat freezing on the project's
   benchmarks, except where the refined grid narrows onto a correlated peak
   and its rounds grow heavy-tailed. Where
   `auto`'s grid trained under a power-law tail, a fixed budget's refining
   rounds are 4x larger on a grid subdivided to 4x the bins (`tail_refining`).
3. **Streaming**, with a tolerance the refining rounds did not meet: the last
   grid, frozen, streams until the tolerance or the budget (sharded over
   devices, `_stream`); the result is that stream's estimate alone (the
   refining rounds count in `n` but not in the mean), whose fresh randomness
   keeps it unbiased whatever the rounds before it showed.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import is_concrete
from .._diagnostics import pareto_k, tail_of
from .._fit._vegas import strata_per_axis
from .._integrand import ratio
from .._progress import report
from .._stats import Estimate, estimate_fields, rounding_floor
from ..fit import VegasPlus
from ..proposals import Grid
from ._blocks import values
from ._sizes import BLOCK, MIN_BLOCKS_TO_STOP


TRAINING_ROUNDS = 10  # VEGAS+ rounds that train the grid, at most (discarded)
MAX_REFINE_ROUNDS = 32  # with a tolerance, adapting rounds after training; then a frozen stream
MIN_STREAM_BLOCKS = 8  # a frozen stream's variance comes from the spread of its rounds
MIN_ROUNDS_TO_STOP = MIN_BLOCKS_TO_STOP  # the refining rounds' too: fewer cannot meet a tolerance


def adaptive_block(budget: int) -> int:
    """Points per VEGAS+ round: about budget/40 as a power of two, 256 to 2^14.

    Small rounds let the grid train for its ten rounds on a quarter of the budget, leaving
    more rounds to refine it; larger rounds than 2^14 gained nothing on the project's
    benchmarks.
    """
    if budget < 16 * 256:
        raise ValueError(f"method='adaptive' needs a budget of at least {16 * 256}, got {budget}.")
    return min(BLOCK, max(256, 1 << int(math.floor(math.log2(budget // 40)))))


def grid_bins(block: int) -> int:
    """Grid bins per axis for rounds of `block` points: `block / 64` (a power of two, rounded
    down), 64 to 256.

    vegas gives its map `neval / 10` increments (at most 1000). Here each bin keeps about
    64 points, so its histogram is not dominated by noise: more bins resolve the integrand
    better until the histogram overfits a round's noise (the cap, chosen on the project's
    benchmarks).
    """
    return min(256, max(64, 1 << (max(1, block // 64).bit_length() - 1)))


# Up to this dimension `auto` trains a fine grid where QMC's values have a power-law tail.
FINE_GRID_MAX_DIM = 6


def fine_grid_bins(block: int) -> int:
    """Grid bins per axis for rounds of `block` points where the integrand's values have a
    power-law tail (a singularity, a narrow peak) in at most `FINE_GRID_MAX_DIM`
    dimensions: `block / 8`, 64 to 256.

    vegas gives its map `neval / 10` increments, whose bins near a singularity or on a
    peak resolve it. In more dimensions the product of more axes' densities makes each
    axis' histogram noisier, so fine bins stop paying (the limit chosen on the project's
    benchmarks); without a power-law tail they overfit (so `auto` refines at `grid_bins`
    there, `VegasPlus.coarse`).
    """
    return max(grid_bins(block), min(256, block // 8))


def is_fine(state, d: int):
    """Whether `auto`'s trained grid (a VEGAS+ `state`) is fine: trained at `fine_grid_bins`
    (in up to `FINE_GRID_MAX_DIM` dimensions) and refined at all of them, not `coarse`
    (QMC's values had a power-law tail). May be traced."""
    return ~state.coarse if d <= FINE_GRID_MAX_DIM else False


@functools.partial(jax.jit, static_argnames="bins")
def uniform_grid(lo, hi, *, bins):
    """`Grid(lo, hi, bins)`, uniform, in one dispatch (eagerly, its checks and casts are a
    sizeable share of a small `integrate` call). `lo < hi` is checked by the caller."""
    return Grid(lo, hi, bins=bins)


# Under a power-law tail, refining rounds of a fixed budget are this many times the
# training's, on a grid holding this many times its bins (`tail_refining`).
TAIL_GROWTH = 4
MAX_TAIL_BINS = 1024
MIN_TAIL_ROUNDS = 6  # fewer larger rounds would leave the scatter too few degrees of freedom


def tail_refining(budget: int, block: int) -> tuple[int, int]:
    """`(rounds, points per round)` of the refining rounds under a power-law tail: the
    `budget` split evenly into rounds of about `TAIL_GROWTH * block` points (a multiple of
    64), or `(0, 0)` where fewer than `MIN_TAIL_ROUNDS` fit.

    vegas, too, refines a map of ~1000 increments per axis on large later iterations. Under a
    power-law tail, a grid with more bins resolves the singularity or peak further, and
    larger rounds keep each finer bin's histogram as well sampled as in training; together
    they beat refining as trained on the project's benchmarks (larger rounds alone did
    not). Without a tail the finer grid only overfits, so there the grid refines as it
    trained (`method="adaptive"`, which knows of no tail, does too).
    """
    rounds = budget // (TAIL_GROWTH * block)
    if rounds < MIN_TAIL_ROUNDS:
        return 0, 0
    # A multiple of 64 points: rounds of an odd size ran markedly slower.
    return rounds, budget // rounds // 64 * 64


def refine_finer(key, state, *, f, batched, rounds, size, progress=False):
    """`refine`'s rounds, all `rounds` of them of `size` points, from a trained `state`
    whose grid is first subdivided (`TAIL_GROWTH` times its bins, at most `MAX_TAIL_BINS`)
    and refined at that resolution from then on (`tail_refining`); the hypercubes' allocation
    starts even. Returns the average (an `Estimate`)."""
    init_key, key = jax.random.split(key)
    finer = _finer(init_key, state, size=size)
    est, _ = refine(key, finer, 0.0, 0.0, f=f, batched=batched, rounds=rounds, tolerant=False,
                    progress=progress)
    return est


@eqx.filter_jit
def _finer(key, state, *, size):
    grid = state.grid
    factor = max(1, min(TAIL_GROWTH, MAX_TAIL_BINS // grid.bins))
    return VegasPlus(diagnostics=False).init(key, grid.subdivided(factor), size)


def training_rounds(budget: int, block: int) -> int:
    """Training rounds of `block` points for a budget: up to a quarter of it, 2 to `TRAINING_ROUNDS`."""
    return max(2, min(TRAINING_ROUNDS, budget // (4 * block)))


def refining_rounds(budget: int, block: int, tolerant: bool) -> int:
    """Refining rounds of `block` points in what the training left of the budget: all of
    it for a fixed budget; with a tolerance at most `MAX_REFINE_ROUNDS` (the rest streams
    on), or all of it when a stream would be too short."""
    rounds = budget // block
    if not tolerant or rounds < MAX_REFINE_ROUNDS + MIN_STREAM_BLOCKS:
        return rounds
    return MAX_REFINE_ROUNDS


def train_vegas_plus(key, f, grid, rounds, block, batched):
    """`rounds` VEGAS+ rounds of `block` points from `grid`: the trained state (estimates
    discarded, so the rounds skip their diagnostics)."""
    rule = VegasPlus(diagnostics=False)
    return vegas_rounds(rule, key, start(rule, key, grid, block=block), rounds, f=f,
                        batched=batched)[1]


@eqx.filter_jit
def start(rule, key, grid, *, block):
    """`rule`'s first state on `grid` for rounds of `block` points (`VegasPlus.init`)."""
    return rule.init(key, grid, block)


def vegas_rounds(rule, key, state, rounds, *, f, batched, fixed=False, progress_total=None,
                 done=0):
    """`rounds` rounds of the VEGAS+ `rule` from `state`: `(their estimates, stacked; the state
    after them; the last round's Samples)`; with `fixed`, each round's state held fixed for
    derivatives (`fixed_for_derivatives`); with `progress_total`, each round's estimate sent
    to the progress bar.

    Traced, one `scan` of `rule.step`; outside `jit`, the same rounds from Python, each as
    three programs, the points (`VegasPlus.propose`), the integrand's values (`values`, the
    one compiled for each integrand) and the update (`VegasPlus.update`)."""
    size = state.draw.u.shape[0]
    if all(is_concrete(a) for a in jax.tree.leaves((key, state, f))):
        parts, samples, run = [], None, _Round.of(rule)
        for i in range(rounds):
            x, points = run.propose(state)
            state, est, samples = run.update(key, i, state, values(x, f=f, batched=batched),
                                             points, fixed=fixed)
            parts.append(est)
            if progress_total is not None:
                report(est.mean, est.stderr, done + (i + 1) * size, total=progress_total,
                       last=i == rounds - 1)
        return _stacked(parts), state, samples

    def one_round(state, i):
        x, points = rule.propose(state)
        state, est, samples = _updated(rule, key, i, state, evaluate_values(x, f, batched),
                                       points, fixed)
        if progress_total is not None:
            jax.debug.callback(functools.partial(_report_round, total=progress_total),
                               est.mean, est.stderr, done + (i + 1) * size, i == rounds - 1)
        return state, (est, samples)

    state, (parts, samples) = jax.lax.scan(one_round, state, jnp.arange(rounds))
    return parts, state, jax.tree.map(lambda a: a[-1], samples)


def evaluate_values(x, f, batched):
    """The integrand at `x`, as `values` computes it (traced: inlined)."""
    return values.__wrapped__(x, f=f, batched=batched)


def _updated(rule, key, i, state, fx, points, fixed):
    state, est, samples = rule.update(key, i, state, fx, points)
    if fixed:  # (the next round's grid is fixed for its derivative)
        state = fixed_for_derivatives(state)
    return state, Estimate(**estimate_fields(est)), samples


class _Round(NamedTuple):
    """A round's two programs run from Python for `rule`: its points (`VegasPlus.propose`)
    and its update (`VegasPlus.update`). The rule's numbers are static, constants as when
    traced, and its arrays (a traced `coarse`) arguments: split once, not per round."""

    numbers: VegasPlus
    arrays: VegasPlus

    @classmethod
    def of(cls, rule: VegasPlus) -> _Round:
        arrays, numbers = eqx.partition(rule, eqx.is_array)
        return cls(numbers, arrays)

    def propose(self, state):
        return _compiled_propose(self.numbers, self.arrays, state)

    def update(self, key, i, state, fx, points, *, fixed):
        return _compiled_update(self.numbers, self.arrays, key, np.int32(i), state, fx, points,
                                fixed)


# (`jax.jit`, not `equinox.filter_jit`, which splits every argument on every call.)
@functools.partial(jax.jit, static_argnums=0)
def _compiled_propose(numbers, arrays, state):
    return eqx.combine(arrays, numbers).propose(state)


@functools.partial(jax.jit, static_argnums=(0, 7))
def _compiled_update(numbers, arrays, key, i, state, fx, points, fixed):
    return _updated(eqx.combine(arrays, numbers), key, i, state, fx, points, fixed)


@jax.jit
def _stacked(parts):
    return jax.tree.map(lambda *a: jnp.stack(a), *parts)


def fixed_for_derivatives(tree):
    r"""`tree` (a density, an adaptation's state) with no derivative through its floats.

    A density fitted to the integrand's values depends on its parameters, but an
    estimate's derivative is taken with the density fixed: for $x_i$ drawn from a
    fixed $q$, $\sum_i w_i\,\partial_\theta f_\theta(x_i)/q(x_i)$ estimates
    $\partial_\theta I$ without bias, and the fit's own derivative (through EM,
    sorting, an optimiser's steps, VEGAS's damped histograms) only adds noise, or
    NaN where $f$ underflows to 0 and $\sqrt{\cdot}$ or $\log$ meets it.
    """
    floats, rest = eqx.partition(tree, eqx.is_inexact_array)
    return eqx.combine(jax.lax.stop_gradient(floats), rest)


def frozen_vegas_plus(state, block: int):
    """What streaming needs of a VEGAS+ state: the grid, the points per hypercube
    its last round allocated for the next, and the hypercubes per axis."""
    return state.grid, state.draw.counts, strata_per_axis(state.grid.dim, block, VegasPlus().max_strata)


def average_rounds(parts: Estimate, done, last_values=None) -> Estimate:
    r"""The first `done` rounds of `parts`, averaged with weights that grow with the round.

    Round $i$ (from 1) gets weight $p_i = i / \sum_j j$: later rounds, drawn from
    better-trained grids, count more, by weights fixed before any round drew, so
    that, each round being unbiased given its grid, the average $\bar I = \sum_i
    p_i I_i$ is unbiased whatever the rounds showed. The variance comes from
    their scatter, $V = \frac{k_e}{k_e - 1} \sum_i p_i^2 (I_i - \bar I)^2$ with
    $k_e = 1/\sum_i p_i^2$ rounds in effect (with $k_e - 1$ degrees of freedom),
    not from the rounds' own error bars
    (i.i.d. bounds when $f/p$ has a power-law tail). Weights from the rounds'
    variances, as vegas uses, drift low when small rounds that starved a region
    report small variances, and the average then misses the truth with too small an
    error bar; weights fixed in advance cannot be pulled so. The Pareto $\hat k$ is
    that of `last_values`, the
    values $f/p$ of the last round (the rounds themselves skip the search for
    their largest values, `VegasPlus(diagnostics=False)`); NaN without them.
    """
    k = parts.mean.shape[0]
    dtype = parts.mean.dtype
    used = jnp.arange(k) < done

    def per_round(a, like):  # a round's figure `(k,)` against `like` `(k, ...)`
        return jnp.reshape(a, (k,) + (1,) * (jnp.ndim(like) - 1))

    def total(a):
        return jnp.sum(jnp.where(per_round(used, a), a, 0), axis=0, dtype=jnp.result_type(a))

    weight = jnp.where(used, jnp.arange(1, k + 1, dtype=dtype), 0)
    p = per_round(weight / jnp.sum(weight), parts.mean)
    mean = jnp.sum(p * parts.mean, axis=0)
    rounds_in_effect = 1 / jnp.sum(p**2, axis=0)
    scatter = jnp.sum(p**2 * (parts.mean - mean) ** 2, axis=0)
    variance = scatter * rounds_in_effect / jnp.maximum(rounds_in_effect - 1, 1)
    # Never below the rounding error of the arithmetic (`jaxmc.stats.rounding_floor`).
    floor = rounding_floor(dtype) * jnp.sum(p * jnp.abs(parts.mean), axis=0)
    return Estimate(
        mean=mean, variance=jnp.maximum(variance, floor**2), n=total(parts.n),
        n_nonfinite=total(parts.n_nonfinite), ess=total(parts.ess),
        n_nonzero=total(parts.n_nonzero),
        pareto_k=(jnp.full(jnp.shape(mean), jnp.nan, dtype) if last_values is None
                  else pareto_k(tail_of(last_values))),
        conservative=jnp.zeros(jnp.shape(mean), bool),
        dof=jnp.maximum(rounds_in_effect - 1, 1),  # a scatter of k_e rounds (Satterthwaite)
    )


def _report_round(mean, stderr, done, last, *, total: int) -> None:
    """Host side: a refining round's estimate to the progress bar."""
    report(mean, stderr, done, total=total, last=bool(last))


def refine(key, state, rtol, atol, *, f, batched, rounds, tolerant, progress=False):
    r"""Up to `rounds` VEGAS+ rounds from a trained `state`, adapting, averaged (`average_rounds`).

    Without a tolerance all `rounds` run; with one, the rounds stop once the average's
    standard error meets $\max(atol, rtol\,|mean|)$, after at least `MIN_ROUNDS_TO_STOP`
    rounds. Returns the average (an `Estimate`) and the final state. With `progress`, each
    round's estimate goes to the progress bar (as `jaxmc.fit.adapt` shows them).
    """
    # The rounds skip their diagnostics; the last round's values give the average's.
    # A grid refined at fewer bins than it holds goes on so (`VegasPlus.coarse`, in the state).
    n = state.draw.u.shape[0]
    rule = VegasPlus(diagnostics=False, coarse_bins=grid_bins(n))
    total = rounds * n if progress else None
    if not tolerant:
        parts, state, last = vegas_rounds(rule, key, state, rounds, f=f, batched=batched,
                                          fixed=True, progress_total=total)
        return _averaged(parts, rounds, last), state
    if all(is_concrete(a) for a in jax.tree.leaves((key, state, f, rtol, atol))):
        # Round by round from Python, as the traced loop below runs them.
        parts, run = None, _Round.of(rule)
        for i in range(rounds):
            x, points = run.propose(state)
            state, est, last = run.update(key, i, state, values(x, f=f, batched=batched),
                                          points, fixed=True)
            parts, met = _recorded(parts, est, np.int32(i), rtol, atol, rounds=rounds)
            if progress:
                report(est.mean, est.stderr, (i + 1) * n, total=total, last=i == rounds - 1)
            if bool(met):
                break
        return _averaged(parts, i + 1, last), state

    def body(loop):
        i, state, parts, _, _ = loop
        x, points = rule.propose(state)
        state, est, last = _updated(rule, key, i, state, evaluate_values(x, f, batched), points,
                                    True)
        if progress:
            jax.debug.callback(functools.partial(_report_round, total=total),
                               est.mean, est.stderr, (i + 1) * n, i == rounds - 1)
        parts, met = _recorded(parts, est, i, rtol, atol, rounds=rounds)
        return i + 1, state, parts, met, last

    shapes = jax.eval_shape(lambda s: _updated(rule, key, 0, s, evaluate_values(
        rule.propose(s)[0], f, batched), rule.propose(s)[1], True), state)
    empty = jax.tree.map(lambda a: jnp.zeros((rounds,) + a.shape, a.dtype), shapes[1])
    no_last = jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), shapes[2])
    done, state, parts, _, last = jax.lax.while_loop(
        lambda loop: (loop[0] < rounds) & ~loop[3], body,
        (jnp.int32(0), state, empty, jnp.asarray(False), no_last))
    return _averaged(parts, done, last), state


@functools.partial(jax.jit, static_argnames="rounds")
def _recorded(parts, est, i, rtol, atol, *, rounds):
    """`parts` (a buffer of `rounds` rounds; `None` to start one) with round `i`'s estimate,
    and whether their average meets the tolerance (after `MIN_ROUNDS_TO_STOP` rounds)."""
    if parts is None:
        parts = jax.tree.map(lambda a: jnp.zeros((rounds,) + a.shape, a.dtype), est)
    parts = jax.tree.map(lambda buffer, x: buffer.at[i].set(x), parts, est)
    average = average_rounds(parts, i + 1)
    met = jnp.all(average.stderr <= jnp.maximum(atol, rtol * jnp.abs(average.mean)))
    return parts, met & (i + 1 >= MIN_ROUNDS_TO_STOP)


@jax.jit
def _averaged(parts, done, last):
    """The rounds' average, its Pareto k-hat from the last round's values $f/p$."""
    return average_rounds(parts, done, ratio(last.fx, jnp.exp(last.log_q))[0])
