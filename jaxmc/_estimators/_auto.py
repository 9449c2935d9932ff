r"""`integrate(method="auto")`: a pilot that measures the candidates and picks the cheapest.

The figure of merit is the cost of a unit of variance. A method whose estimate
from $m$ evaluations has variance $\sigma^2_m$ has *variance per evaluation*
$v = m\,\sigma^2_m$; spending the remaining $n$ evaluations on it gives
variance about $v/n$, at a cost proportional to $c\,n$ with $c$ its time per
evaluation, so the winner minimises $v \cdot c$.

The candidates:

- `"qmc"`: `QMC_REPLICAS` scrambled Sobol' nets (`_pilot_nets`): their spread's variance
  per evaluation, projected to the stream's net size at the rate the nets show; a clear win
  over plain Monte Carlo on the same points (a smooth integrand) skips the other candidates
  (as does the grid's outlook, below, in or out of sample, `_held_out`), decided on the nets'
  first quarter where it is already plain, else on the whole nets; where $f$ is a product of
  one-dimensional factors (`separable`), which the grid fits exactly, only on the first
  quarter and by a wider margin, and the grid's screen does not drop it.
- `"adaptive"`: the VEGAS+ grid trained as `method="adaptive"` would train it
  (`jaxmc.fit.VegasPlus`, ten rounds on at most a quarter of the budget), $\sigma^2_m$ of its
  last round (`_pilot_grid.grid_rounds`), hedged (a geometric mean) with the scatter of its
  last `SCATTER_ROUNDS` rounds' means where that round's own variance is `SCATTER_TRUST` times
  above it: a round's variance comes from pairs of points in hypercubes, which a peak the grid
  has not yet resolved inflates (100-1000x what the grid then realised on a 16-D camel, a 5-D
  posterior and a corner singularity). It is not trained at all where a product density fitted
  to QMC's values would cost `OUTLOOK_MARGIN` times QMC, or more than QMC where it gains
  little over plain MC (`outlook_drops_grid`). A young grid's variance says little of the
  trained one's (`run_pilot`), so the grid is dropped after `SCREEN_ROUNDS` rounds only when,
  as it stands, it is `SCREEN_MARGIN` times costlier than a QMC pilot that measured the
  integrand, and never when QMC's values have a power-law tail (a young grid's rounds are then
  as heavy-tailed: $x^{-1/2}$ in 2-D measured 35-110 after 3 rounds, 0.4-0.6 after 10; a young
  grid on the 8-D i-flow Gaussian measured 80 against QMC's 18, then trained to 0.35);
  otherwise it trains in full and the choice is made on the trained grid (a tail its last round
  reads is QMC's too, `tail_through_grid`). Under such a tail, in up to `FINE_GRID_MAX_DIM`
  dimensions, its bins are `fine_grid_bins` (as vegas's many increments, they resolve a
  singularity: 2.5x and 9x lower variance at 1e5). If the grid wins it refines as
  `method="adaptive"` does after training (under the tail on larger rounds and 4x the bins,
  `tail_refining`, for which its figure is credited, `credited_for_refining`), with a tolerance
  then streams frozen; else training was the price of knowing.
- `"grid_qmc"`: QMC's nets carried through the trained grid's map, $x = G(u)$ with values $f/q$
  (`grid_qmc_pilot`: `QMC_REPLICAS` nets as large as QMC's pilot's, measured and projected as
  its are): importance sampling from the grid, with QMC's rate on what is left, $f/q$, flatter
  and smoother than $f$ where the grid fits. It streams as `method="qmc"` does, on the frozen
  grid. Measured at $10^5$ (16 keys, RMS relative error, against `method="adaptive"`, which
  starts from the same training): Genz's 8-D corner peak 8.3e-6 against 4.4e-4, his 16-D one
  3.8e-5 against 4.1e-4, his 8-D continuous 9.6e-6 against 4.7e-4, vegas's 4-D Gaussian 1.3e-4
  against 2.0e-3, i-flow's 8-D Gaussian 2.7e-4 against 1.1e-3. It is a candidate only where it
  fits: plain Monte Carlo's variance through the grid below `GRID_QMC_MAX_VARIANCE` (a grid that
  loose goes on adapting, a frozen one does not: the 10-D ball's measured 25-170, and QMC
  through it erred 10x as much as the refined grid), and values $f/q$ with no power-law tail
  (`QMCFigures.heavy`; the refining grid's rounds then give a tighter honest error bar). A grid
  that follows a singularity on a face has its bins there follow it (`_edged_grid`), $f/q$
  bounded (RMS error, 40 keys at 1e5, against the refining grid's: x^-1/3 in 6-D 2.7e-5 / 5.7e-4,
  x^-1/2 in 2-D 5.3e-6 / 4.8e-4).
- `"mixture"`: a Gaussian mixture seeded from the trained grid's last round (`_seeded_mixture`:
  `GaussianMixture.from_samples` on the weights $|f|\,w/q$, EM towards the density
  $\propto |f|$, `MIXTURE_COMPONENTS` diagonal components), mixed with the grid itself at
  `DEFENSIVE_SHARE` (defensive importance sampling, Hesterberg 1995), measured on up to
  `MIXTURE_PILOT_POINTS` points, each part drawing its share of them
  (`Mixture(..., stratified=True)`: no point is drawn twice, once by each part, and then chosen
  between them).
  A grid can lock onto one of several separated peaks, and the mixture seeded from it with it:
  before it is measured, an ascent of $\log|f|$ from the QMC pilot's best points
  (`_mode_search`, where JAX can differentiate $f$) finds the modes near them, and a mode where
  the mixture's density falls far short of the integrand gets a Gaussian of its own (i-flow's
  16-D camel at $10^5$: 7 keys of 10 had held one of its two modes, estimates half the truth at
  5-750 standard errors; with the search, 10 of 10 within 2). Before the search and those points
  are paid for, the seeded mixture is judged on the grid's own points (`mixture_outlook`, no
  evaluation of $f$), and not measured where it would cost `MIXTURE_HOPELESS` times QMC or the
  grid; not even seeded where the grid follows a singularity (`follows_a_singularity`):
  Gaussians do not. A grid is a product of axis densities: a peak along a diagonal, or several
  peaks, make it put mass on every combination of the axes' bins, which a mixture of Gaussians
  does not (measured, variance per evaluation against the trained grid's at $10^5$: 80-3e5x
  lower on a correlated 5-D posterior, 5-8x on vegas's and i-flow's Gaussians and camels, but
  100-200x higher on broad Genz peaks and the corner peak, where the grid wins). Its values are
  bounded wherever the grid's are, $p \ge 0.1\,q_{grid}$ giving $E_p[(f/p)^2] \le
  10\,E_{q_{grid}}[(f/q_{grid})^2]$, so a heavy-looking tail does not disqualify its pilot (on
  the posterior the pilot's Pareto $\hat k$ is 0.4-0.75 at variances 100x and more below the
  grid's); but it is a candidate only if it fits well, relative variance per evaluation below
  `_pilot_mixture.MIXTURE_MAX_VARIANCE`: the grid's figure is its last training round's, and the
  grid goes on adapting (on the 10-D ball it measured 200-2000 and then ran at ~4). Unless the
  grid itself falls `UNDERCOVERED` times short of $|f|/\hat I$ at a mode the search found
  (`grid_misses_a_mode`): its figure then hides mass it does not sample, and it is no candidate
  against a mixture with a figure, loose or not (on the 16-D camel at $10^5$, 24 keys: 2 had
  taken the grid, one measured at 1.3e3 against a loose mixture's 85, and returned half the
  truth, at up to 219 standard errors; none do now, RMS error 0.11 -> 1.8e-3; two 4-D Gaussians
  on the diagonal: the grid had won on 15 keys of 24, now the mixture on all, RMS error 1.9e-3
  -> 9.8e-4; 5-D posterior 6.0e-3 -> 4.3e-3). If the mixture wins, it adapts too, twice:
  refitted to its pilot's points, then to a tenth of the rest of the budget drawn from that
  refit (`adapted_mixture`: population Monte Carlo; 6-26x lower variance on the posterior, the
  16-D camel and the 10-D ball), each refit with a wide Gaussian among its parts that bounds the
  weights where the fitted ones fall faster than $f$ (`_with_wide_gaussian`). What is left
  streams from it (`method="importance"` blocks of `_stream`), to the budget or the tolerance.
- `"ridge_qmc"`: QMC's nets through a density along one direction, for a ridge function
  $g(w \cdot x)$ (a resonance off the axes), which neither a product of axis densities nor
  QMC's nets follow: measured where QMC won, not clearly (`_pilot_ridge`).
- `"corner_qmc"`: QMC's nets through the cube bent towards a corner where $f$ is singular,
  $x_j = z_j^p$ on the axes that meet there (`_corner`), for a point singularity that no
  face's power shows ($(\sum_j x_j)^{-3/2}$, whose marginals are bounded): sought where QMC's
  values or the grid's rounds show a power-law tail (`_pilot_corner`).

The times per evaluation $c$ are fixed ratios (`RELATIVE_COST`), not clock readings, so
`"auto"` is deterministic in `(key, n)`: the grid's map, its training and the stratified
allocation make a VEGAS+ evaluation of a cheap integrand 4-7x dearer than a Sobol' point on a
CPU (0.17 s against 0.04 s per $10^6$ in 4-D, steady state), and about as dear for an
integrand that costs more than the map; 3 sits between. A Sobol' point carried through the
grid's map cost 2.4-4x a bare one ($10^6$ points in 4-16 D, cheap integrands): 2. A draw from
the mixture inverts truncated normal CDFs and evaluates both its parts' densities at every
point: 0.17-0.74 s per $10^6$ in 2-16 D (float64, 8 components, a 256-bin grid), and a whole
`"auto"` call at $10^6$ that streamed from it took 1.7-2.3x as long as `method="adaptive"` on
vegas's 4-D and i-flow's 8-D Gaussians (3-5x when 12 was set). 12 keeps the mixture for the
large gains (100-1000x on a correlated posterior), not close calls. The pilot's evaluations
count in the result's `n` but not in its mean: the streamed estimate uses fresh
randomness, independent of the choice, so it stays unbiased.
"""
from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import is_concrete
from ._adaptive import FINE_GRID_MAX_DIM, fine_grid_bins, grid_bins, tail_refining, uniform_grid
from ._edged_grid import edged_if_singular
from ._held_out import held_out_drops_grid
from ._mode_search import search_evaluations
from ._pilot_choice import (  # (CANDIDATES to SCREEN_MARGIN: the rules, read there)
    CANDIDATES,
    MIXTURE_FLOOR,
    MIXTURE_HOPELESS,
    OUTLOOK_COSTS,
    RELATIVE_COST,
    SCREEN_MARGIN,
    after_training,
    mixture_hopeless,
    qmc_alone,
    screen_young_grid,
    with_mixture,
)
from ._pilot_corner import seek_corner, with_corner_candidate
from ._pilot_grid import (
    credited_for_refining,
    grid_qmc_pilot,
    grid_rounds,
    run_rounds,
    staged_grid_rounds,
    tail_through_grid,
)
from ._pilot_mixture import mixture_outlook, mixture_pilot
from ._pilot_nets import (
    EARLY_MARGIN,
    MAX_NET_GROWTH,
    clear_win_gain,
    early_look_figures,
    net_values,
    outlook_drops_grid,
    pilot_qmc_points,
    whole_nets_figures,
)
from ._pilot_record import Pilot
from ._pilot_ridge import ridge_probe, room_for_a_ridge, with_ridge_candidate
from ._plan import QMC_REPLICAS, final_net


__all__ = ["CANDIDATES", "MIXTURE_FLOOR", "MIXTURE_HOPELESS", "MIXTURE_PILOT_POINTS",
           "OUTLOOK_COSTS", "RELATIVE_COST", "SCREEN_MARGIN", "SCREEN_ROUNDS", "run_pilot",
           "split_keys"]

MIXTURE_PILOT_POINTS = 4096  # at most this many points measure it
SCREEN_ROUNDS = 3  # VEGAS+ rounds before the grid may be dropped without full training


def _qmc_early_look(key, lo, hi, *, f, per_replica, growth, batched):
    """The first quarter of the pilot's nets (`per_replica // 4` points each), measured: `(their
    values and bins, whether QMC wins clearly by `EARLY_MARGIN` times their bar or the grid's
    outlook on them drops it (`outlook_drops_grid`, `held_out_drops_grid`), its lone `Pilot`,
    whether it leaves room for a ridge, `room_for_a_ridge`, whether the values have a
    power-law tail)`."""
    quarter = per_replica // 4
    y, bins = net_values(key, lo, hi, f, batched, 0, 1, quarter.bit_length() - 1, True)
    return (y, bins) + _early_verdict(bins, y, growth=growth,
                                      bar=EARLY_MARGIN * clear_win_gain(quarter))


# The figures of the QMC pilot's values, one compiled program for every integrand of their
# shapes (as every figure of the pilot's: only the values are compiled for each integrand).
@partial(jax.jit, static_argnames=("growth", "bar"))
def _early_verdict(bins, y, *, growth, bar):
    qmc = early_look_figures(bins, y, growth, bar)
    stop = qmc.clear_win | outlook_drops_grid(qmc, *OUTLOOK_COSTS) | held_out_drops_grid(qmc, bins, y)
    return stop, qmc_alone(qmc, y.shape[1] * QMC_REPLICAS), room_for_a_ridge(qmc.variance,
                                                                         qmc.clear_win), qmc.heavy


def _qmc_pilot(key, lo, hi, early, early_stop, *, f, per_replica, growth, batched):
    """`QMC_REPLICAS` scrambled Sobol' nets of `per_replica` points, measured: `(QMCFigures,
    QMC's lone `Pilot`, whether they drop the grid, `outlook_drops_grid`)`. `early`,
    `early_stop`: their first quarter's values and bins, and its verdict (`_qmc_early_look`);
    the rest is evaluated here; an early choice of QMC stands."""
    rest = net_values(key, lo, hi, f, batched, 1, 3, (per_replica // 4).bit_length() - 1, True)
    return _qmc_figures(early, rest, early_stop, growth=growth, bar=clear_win_gain(per_replica))


@partial(jax.jit, static_argnames=("growth", "bar"))
def _qmc_figures(early, rest, early_stop, *, growth, bar):
    y, bins = (jnp.concatenate(parts, axis=1) for parts in zip(early, rest))
    qmc = whole_nets_figures(bins, y, early_stop, growth, bar)
    return qmc, qmc_alone(qmc, y.shape[1] * QMC_REPLICAS), outlook_drops_grid(qmc, *OUTLOOK_COSTS)


@jax.jit
def split_keys(key):
    """`(the stream's key, the pilot's four keys)` from `integrate`'s key, in one dispatch
    (eagerly, the splits and their unpacking cost ~0.1 ms)."""
    pilot_key, key = jax.random.split(key)
    return key, tuple(jax.random.split(pilot_key, 4))


def run_pilot(keys, f, lo, hi, budget, batched, rounds, round_size, tolerant=False):
    """Run the candidates' pilots (`keys`: the pilot's four, `split_keys`); returns
    `(Pilot, trained VEGAS+ state or None, (seeded mixture, its pilot's points and values)
    or None, evaluations left for the winner's stream)`. `tolerant`: the stream stops at a
    tolerance (then a grid streams frozen after refining, and is not credited for it).

    The grid trains in two stages, `SCREEN_ROUNDS` rounds and then the rest of the
    `rounds` rounds of `round_size` that `method="adaptive"` trains for (all in one where
    QMC's values have a power-law tail, which the screen never drops): a young
    grid's variance says little of the trained one's (measured after 3 and 10
    rounds: from 10x worse, on a 16-D discontinuity, to 1000x better, on a 5-D
    posterior), so the choice is made on the trained grid unless the young one,
    as it stands, is `SCREEN_MARGIN` times costlier than QMC.
    QMC through the trained grid is measured on nets as large as QMC's pilot's.
    The mixture is seeded from the trained grid and measured on at most
    `MIXTURE_PILOT_POINTS` points, unless another candidate already costs less than a
    mixture at `MIXTURE_FLOOR` would, or the grid follows a singularity, or the mixture's
    figure on the grid's points costs `MIXTURE_HOPELESS` times QMC's or the grid's, or in
    one dimension (a grid there is any piecewise-constant density). With a tolerance too:
    on the 5-D posterior at `rtol=1e-3` (32 keys) the refitted mixture with its wide part
    met it in 0.82M evaluations (median; at most 3.4M, vegas 1.5M) with no z below -2.4
    (mean -0.8), where the grid's stream took 3.3M (at most 14M over 40 keys, one
    z at -3.3); the seeded mixture alone, before the refit, had stopped low on a
    spread that missed its weights' tail (8 keys: mean z -1.6, one at -4.3).
    When QMC's pilot beats plain MC on the same points by `clear_win_gain` per evaluation (a
    smooth integrand), or the grid's outlook on them is hopeless (`outlook_drops_grid`), no grid
    is trained at all; where the nets' first quarter shows `EARLY_MARGIN` times that gain, or
    drops the grid so, the rest of them go unevaluated (shortcuts are taken outside `jit` only).

    A ridge function's density (`"ridge_qmc"`, `_pilot_ridge`) and the cube bent towards a
    singular corner (`"corner_qmc"`, `_pilot_corner`) join the candidates at the end; where
    one wins, the second slot holds the map it streams through.

    The stream's budget depends only on how far the pilot went, QMC's early look,
    screening or training, not on whether a shortcut then skipped the grid or the mixture
    (their points are left unspent): the stream's sizes are static, so every
    budget it takes is one more compiled program (~1-2 s, against 0.01-0.1 s
    a run at 1e5-1e6), and keys that take different shortcuts share the winner's.
    """
    per_replica = pilot_qmc_points(budget)
    # The first quarter of the nets may already decide for QMC: the rest of the pilot's
    # points then go to the stream (at 1e5, 3 nets of 2^15 instead of 5 of 2^14).
    early_rest = budget - per_replica * QMC_REPLICAS // 4
    early_growth = min(final_net(early_rest) / (per_replica // 4), MAX_NET_GROWTH)
    look = _qmc_early_look(keys[0], lo, hi, f=f, per_replica=per_replica, growth=early_growth,
                           batched=batched)
    early, _, early_stop, alone, room, heavy = look
    probe = (ridge_probe(keys[0], f, lo, hi, early, batched=batched, per_replica=per_replica)
             if is_concrete(room) and bool(room) else None)
    if is_concrete(early_stop) and bool(early_stop):
        result, tail = (alone, None, None, early_rest), heavy
    else:
        result, tail = _pilot_after_early_look(keys, f, lo, hi, budget, batched, rounds,
                                               round_size, tolerant, look, per_replica)
        tail = tail | heavy
    if probe is not None:
        result = with_ridge_candidate(result, keys[0], f, lo, hi, probe, batched=batched,
                                      budget=budget, per_replica=per_replica)
    if is_concrete(tail) and bool(tail):  # (an unbounded integrand: seek its corner)
        corner = seek_corner(keys[0], f, lo, hi, early, batched=batched, per_replica=per_replica)
        result = with_corner_candidate(result, keys[0], f, lo, hi, corner, batched=batched,
                                       per_replica=per_replica)
    return result


def _pilot_after_early_look(keys, f, lo, hi, budget, batched, rounds, round_size, tolerant,
                            look, per_replica):
    """`run_pilot` on from QMC's early look where it did not choose QMC (`look`, its
    results, `_qmc_early_look`, on nets of `per_replica` points): `(its result, whether QMC's
    values or the grid's rounds showed a power-law tail)`."""
    early, early_bins, early_stop, alone = look[:4]
    qmc_n = per_replica * QMC_REPLICAS
    key_qmc, key_screen, key_train, key_mixture = keys
    screen = min(SCREEN_ROUNDS, rounds)
    screened_rest = budget - qmc_n - screen * round_size  # after a clear win or a screen
    # In one dimension a grid is any piecewise-constant density: a mixture adds nothing.
    mixture_n = 0 if lo.size == 1 else min(round_size, MIXTURE_PILOT_POINTS)
    growth = min(final_net(screened_rest) / per_replica, MAX_NET_GROWTH)
    qmc, alone, unpromising = _qmc_pilot(key_qmc, lo, hi, (early, early_bins), early_stop, f=f,
                                         per_replica=per_replica, growth=growth, batched=batched)
    if is_concrete(qmc.clear_win) and (bool(qmc.clear_win) or bool(unpromising)):
        return (alone, None, None, screened_rest), qmc.heavy
    # Fine bins under a power-law tail, held either way (`VegasPlus.coarse`: may be traced).
    bins = fine_grid_bins if lo.size <= FINE_GRID_MAX_DIM else grid_bins
    coarse, grid = ~qmc.heavy, uniform_grid(lo, hi, bins=bins(round_size))
    settings = dict(f=f, rounds=rounds, round_size=round_size, batched=batched)
    if rounds > screen and is_concrete(qmc.heavy) and bool(qmc.heavy):
        # The screen never drops a grid under a power-law tail: both stages in one program,
        # the same rounds (at 1e5, ~0.8 ms of a run less).
        # (NumPy placeholders for the screen's figures, traced as its arrays were: no dispatch.)
        unread = np.full((len(CANDIDATES),), np.inf, qmc.variance.dtype)
        screened, decided = (unread, unread, np.asarray(0, np.int32)), np.asarray(False)
        v_grid, grid_blind, grid_tail, state, samples = staged_grid_rounds(
            (key_screen, key_train), grid, screen, coarse, **settings)
    else:
        parts, state, samples = run_rounds(key_screen, grid, jnp.int32(screen), coarse, **settings)
        (v_grid, grid_blind), screened, screened_two, decided = screen_young_grid(
            qmc, parts, samples, jnp.int32(screen), rounds=rounds, round_size=round_size)
        if is_concrete(decided) and bool(decided):
            variance, cost, choice = screened_two
            pilot = Pilot(CANDIDATES[:2], variance, cost, choice, (qmc_n, screen * round_size))
            return (pilot, state, None, screened_rest), qmc.heavy
        if rounds > screen:
            v_grid, grid_blind, grid_tail, state, samples = grid_rounds(
                key_train, state.grid, jnp.int32(rounds - screen), coarse, **settings)
    if rounds > screen:
        qmc = tail_through_grid(qmc, grid_tail)  # (a tail its nets missed)
    # The search for modes the mixture missed is budgeted whether or not it runs (it needs
    # the integrand's gradients; as a shortcut's, its evaluations are then left unspent).
    search_n = search_evaluations(lo.size) if mixture_n else 0
    grid_qmc_n = qmc_n  # QMC through the trained grid: nets as large as QMC's pilot's
    trained_rest = budget - qmc_n - rounds * round_size - grid_qmc_n - mixture_n - search_n
    grid_qmc = grid_qmc_pilot(  # (on a key of its own; bent at singular faces, `_edged_grid`)
        jax.random.fold_in(key_train, 1), edged_if_singular(state.grid), f=f, per_replica=per_replica,
        growth=min(final_net(trained_rest) / per_replica, MAX_NET_GROWTH), batched=batched,
    )
    trained_n = (qmc_n, rounds * round_size, grid_qmc_n)
    if lo.size <= FINE_GRID_MAX_DIM and not tolerant and tail_refining(trained_rest, round_size)[0]:
        v_grid = credited_for_refining(v_grid, ~coarse, qmc, grid_qmc)  # (`is_fine`: refines on)
    # No mixture measured so far has gone below MIXTURE_FLOOR: when another candidate already
    # costs less, or the grid follows a singularity, none is fitted (outside jit only).
    (variance, cost, choice), beaten = after_training(qmc, v_grid, grid_blind, grid_qmc,
                                                       screened, decided)
    without_mixture = Pilot(CANDIDATES[:3], variance, cost, choice, trained_n)
    if mixture_n == 0 or (is_concrete(beaten) and bool(beaten)):
        return (without_mixture, state, None, trained_rest), qmc.heavy
    # The mixture seeded from the grid, judged on the grid's points before the search for
    # modes and its own points are paid for: hopeless, it is not measured (outside jit).
    mixture, outlook = mixture_outlook(state.grid, samples)
    hopeless = mixture_hopeless(outlook, cost)
    if is_concrete(hopeless) and bool(hopeless):
        return (without_mixture, state, None, trained_rest), qmc.heavy
    v_mixture, mixture_blind, mixture, draws, searched, grid_misses = mixture_pilot(
        key_mixture, mixture, state.grid, samples, key_qmc, early, f=f, size=mixture_n,
        batched=batched,
    )
    variance, cost, choice = with_mixture(qmc, v_grid, grid_blind, grid_qmc, v_mixture,
                                           mixture_blind, grid_misses, screened, decided)
    evaluations = trained_n + (mixture_n + (search_n if searched else 0),)
    pilot = Pilot(CANDIDATES, variance, cost, choice, evaluations)
    return (pilot, state, (mixture, draws), trained_rest), qmc.heavy
