r"""The VEGAS+ grid in `integrate(method="auto")`'s pilot: its training rounds, measured
(`grid_rounds`), and QMC's nets carried through the trained grid (`grid_qmc_pilot`)."""
from __future__ import annotations

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp

from .._diagnostics import bounded_variance, power_law_tail, tail_of
from .._integrand import ratio
from ..fit import Integrand, VegasPlus, run_adaptation
from ._adaptive import grid_bins
from ._corner import CornerMap
from ._edged_grid import EdgedGrid
from ._pilot_nets import QMCFigures, capped, grid_net_values, measure_nets, relative_variance


# The trained grid's figure: its last round's variance, unless that is SCATTER_TRUST times
# the scatter of the last SCATTER_ROUNDS rounds' means; then the geometric mean of the two.
# A round's variance is a sum over hypercubes of two or three points each: on a peak the
# grid has not yet resolved, a few hypercubes' pairs carry it. Measured at 1e6 (4 keys;
# relative variance per evaluation): last round / scatter / what `method="adaptive"` then
# realised: i-flow camel 16-D 3e5-2e6 / 47-1000 / 376; 5-D posterior 550-1400 / 3-220 /
# 2.6; 4-D corner singularity 0.35-0.5 / 0.001-0.013 / 0.009; elsewhere within 3x of each
# other. But the scatter of 5 rounds has 4 degrees of freedom: an honest round variance is
# 10x its scatter in 1.7% of runs (chi-square), 30x in 0.2%; at 10x, 2 of the `auto`
# benchmark's 660 runs (vegas's 4-D Gaussian, the 3-D ball) left the mixture or QMC for a
# grid that then erred 5x as much. Hence 30x, and the geometric mean.
SCATTER_ROUNDS = 5
SCATTER_TRUST = 30.0
# QMC through the grid is a candidate only below this relative variance per evaluation of
# plain MC through it: as `_pilot_mixture.MIXTURE_MAX_VARIANCE`, an effective sample size
# above n/10.
GRID_QMC_MAX_VARIANCE = 9.0
# ...and $f/q$ is not taken for a power-law tail where QMC's nets through the grid beat plain
# MC on their points by this much (the whole nets' spread, before any projection): a tail
# that carried the error would not let them. Bounded peaks read a Pareto k-hat near 0.2
# through the grid, and over it by chance: Genz's 8-D corner peak at 1e6, one key of 10 at
# 0.203, which then streamed from the grid alone at 100x the error (1.1e-4 against ~1e-6);
# there the gain was 780-7000 (10 keys). The singularities' stayed below 50 at 1e5 (84 runs:
# x^-1/3 in 6-D, (sum x)^-3/2 in 4-D, x^-1/2 in 2-D) and 214 at 1e6 (60 runs).
GRID_QMC_TAIL_GAIN = 500.0


def grid_rounds(key, grid, active, coarse=False, *, f, rounds, round_size, batched):
    """The first `active` of `rounds` VEGAS+ rounds from `grid` (`run_rounds`), measured:
    the last round's relative variance per evaluation, whether it saw only zeros, whether its
    values have a power-law tail (`round_figures`), the state after it and its `Samples`."""
    parts, state, samples = run_rounds(key, grid, active, coarse, f=f, rounds=rounds,
                                       round_size=round_size, batched=batched)
    figures = _round_figures(parts, samples, active, rounds=rounds, round_size=round_size)
    return figures + (state, samples)


@eqx.filter_jit
def staged_grid_rounds(keys, grid, first, coarse=False, *, f, rounds, round_size, batched):
    """`grid_rounds` in two stages, as `auto`'s pilot trains: the first `first` rounds from
    `grid` on `keys[0]`, then the rest from the grid they trained (its allocation anew) on
    `keys[1]`; one compiled program, for where nothing is decided between the stages."""
    settings = dict(f=f, rounds=rounds, round_size=round_size, batched=batched)
    _, state, _ = run_rounds(keys[0], grid, jnp.int32(first), coarse, **settings)
    return grid_rounds(keys[1], state.grid, jnp.int32(rounds - first), coarse, **settings)


@eqx.filter_jit
def run_rounds(key, grid, active, coarse=False, *, f, rounds, round_size, batched):
    """The first `active` of `rounds` VEGAS+ rounds from `grid` (`run_adaptation`, the rest
    skipped, so one compiled program serves the screening and the training stage: ~1.5 s
    of a first call): `(the rounds' estimates, the state after the last, its `Samples`)`.
    With `coarse` (may be traced), a grid of more bins than `grid_bins(round_size)` is
    refined at that many (`VegasPlus.coarse`). The rounds are compiled for each integrand,
    their figures (`round_figures`) once for every integrand of their shapes."""
    # The rounds skip their diagnostics: only the last one's variance is read, bounded in
    # `round_figures` from its values as its diagnostics would have bounded it.
    rule = VegasPlus(diagnostics=False, coarse_bins=grid_bins(round_size), coarse=coarse)
    return run_adaptation(rule, key, Integrand(f, batched), grid, rounds, round_size,
                          keep_samples=True, active=active)


def round_figures(parts, samples, active, *, rounds, round_size):
    """`run_rounds`'s figures (traceable; `grid_rounds` compiles them alone, `integrate`'s
    pilot with what it decides from them): the last round's relative variance per
    evaluation (hedged by the recent rounds' scatter, see `SCATTER_TRUST`), whether it
    saw only zeros, and whether its values $f/q$ have a power-law tail (`tail_through_grid`)."""
    last = active - 1
    values, _ = ratio(samples.fx, jnp.exp(samples.log_q))
    tail = tail_of(values)
    variance, _ = bounded_variance(parts.variance[last], parts.mean[last], tail)
    v_last = relative_variance(parts.mean[last], variance) * round_size
    # The scatter of the last SCATTER_ROUNDS rounds' means (the spread `method="adaptive"`
    # reports its error from), where the last round's own variance is far above it.
    index = jnp.arange(rounds)
    recent = (index > last - SCATTER_ROUNDS) & (index <= last)
    shape = (rounds,) + (1,) * (parts.mean.ndim - 1)
    weight = jnp.reshape(recent, shape).astype(parts.mean.dtype) / SCATTER_ROUNDS
    centre = jnp.sum(weight * parts.mean, axis=0)
    spread = jnp.sum(weight * (parts.mean - centre) ** 2, axis=0) * SCATTER_ROUNDS / (SCATTER_ROUNDS - 1)
    v_scatter = relative_variance(centre, spread) * round_size
    heavy = (active >= SCATTER_ROUNDS) & (v_last > SCATTER_TRUST * v_scatter)
    hedged = jnp.sqrt(v_last * v_scatter)  # the scatter of 5 rounds is itself uncertain
    return (jnp.where(heavy, hedged, v_last), jnp.all(parts.mean[last] == 0),
            jnp.any(power_law_tail(tail)))


_round_figures = partial(jax.jit, static_argnames=("rounds", "round_size"))(round_figures)


@jax.jit
def tail_through_grid(qmc: QMCFigures, grid_tail) -> QMCFigures:
    r"""QMC's pilot figures `qmc`, told whether the trained grid's last round read a power-law
    tail of $f/q$ (`grid_tail`, `round_figures`): where it did and QMC's own values showed
    none, QMC's variance is credited with plain MC's on its points, as under its own tail
    (`measure_nets`), and `heavy` is set.

    A grid's density lies between bounds, so $f/q$ and $f$ share a tail, and the grid's round
    reads it on more values than QMC's nets (16,384 against 32,768 at 1e6, but from a density
    that samples the tail more often): Pareto $\hat k$ is uncertain by about 0.1 on either.
    $x^{-1/3}$ in 6-D at 1e6 (16 keys) read 0.19 on QMC's nets on 2 keys, whose replicas'
    spread then claimed 0.065-0.10 per evaluation against the trained grid's 0.17-0.20, and
    QMC erred 5e-4-1e-3 where the refining grid errs 8e-5."""
    told = grid_tail & ~qmc.heavy
    variance = jnp.where(told, jnp.maximum(qmc.variance, qmc.plain), qmc.variance)
    return eqx.tree_at(lambda q: (q.variance, q.heavy), qmc, (variance, qmc.heavy | told))


# Under a singularity the refining stream realises this many times less variance per
# evaluation than the trained grid's figure, or more (`credited_for_refining`).
TAIL_REFINING_GAIN = 4.0


@jax.jit
def credited_for_refining(v_grid, fine, qmc: QMCFigures, grid_qmc: QMCFigures):
    r"""The trained grid's figure `v_grid`, divided by `TAIL_REFINING_GAIN` where it follows a
    singularity: a `fine` grid (`is_fine`: QMC's values had a power-law tail) through which
    $f/q$ keeps one (`grid_qmc.heavy`). The caller credits it only where the stream then
    refines finer (`tail_refining`: 4x the bins on 4x the rounds' points, no tolerance).

    The figure is the last training round's; the stream refines on. Over keys 200-239, the
    median figure against the stream's realised relative variance per evaluation: $x^{-1/3}$
    in 6-D 0.13 / 0.031 at 1e5 and 0.16 / 0.0082 at 1e6, $(\sum x)^{-3/2}$ in 4-D 0.038 /
    0.0055 and 0.031 / 0.0022, $x^{-1/2}$ in 2-D 0.30 / 0.017 and 0.35 / 0.0038 (4.4-90x).
    Uncredited, a round that drew a large value made QMC look as cheap: at 1e5, $x^{-1/2}$
    took QMC on 3 keys of 80, which erred 4e-3, 10x the grid (credited, none: RMS error
    7.1e-4 -> 4.7e-4 on keys 20-79), $(\sum x)^{-3/2}$ on 7 keys of 40 (RMS error 5.6e-4
    against the grid's 2.4e-4; credited, 2, both QMC's early look, which this does not reach)."""
    singular = fine & grid_qmc.heavy & ~qmc.blind
    return jnp.where(singular, v_grid / TAIL_REFINING_GAIN, v_grid)


def grid_qmc_pilot(key, grid, *, f, per_replica, growth, batched):
    """`QMC_REPLICAS` scrambled Sobol' nets of `per_replica` points through the trained
    `grid`'s map, measured as QMC's pilot is (`measure_nets`, projected to nets `growth`
    times larger): `QMCFigures` (its `clear_win` unused), the variance `inf` where the grid
    fits loosely (plain MC's through it above `GRID_QMC_MAX_VARIANCE`: the grid goes on
    adapting, QMC through it would not) or $f/q$ has a power-law tail (the replicas' spread
    understates, the refining grid gives the tighter honest error bar; see `_auto`), unless
    the nets beat plain MC by `GRID_QMC_TAIL_GAIN`, or the map is bent to a singularity (a
    grid on a face, an `EdgedGrid` that is `powered`; the cube at a corner, a `CornerMap`) and
    the values reach a cap (`capped`)."""
    y = grid_net_values(key, grid, f, batched, per_replica.bit_length() - 1)
    bent = grid.powered if isinstance(grid, (EdgedGrid, CornerMap)) else jnp.asarray(False)
    return _grid_qmc_figures(y, bent, growth=growth)


@partial(jax.jit, static_argnames="growth")
def _grid_qmc_figures(y, bent, *, growth):
    figures = measure_nets(y, growth, jnp.inf, GRID_QMC_TAIL_GAIN)
    # Through a grid bent to a face's singularity, with powers raised above the grid's
    # slope, f/q is bounded there; on a few thousand values the skew of the bins' masses
    # then reads as a tail (x^-1/2 in 2-D: k-hat 0.7-0.9 on 4096 values, the
    # largest 1.1x the tenth; -0.2 to -0.45 on 32768), which a cap tells apart.
    heavy = figures.heavy & ~(bent & capped(y))
    loose = figures.plain > GRID_QMC_MAX_VARIANCE
    variance = jnp.where(loose | heavy, jnp.inf, figures.variance)
    return eqx.tree_at(lambda q: (q.variance, q.heavy), figures, (variance, heavy))
