r"""`integrate(method="auto")`: a pilot that measures the candidates and picks the cheapest.

The figure of merit is the cost of a unit of variance. A method whose estimate
from $m$ evaluations has variance $\sigma^2_m$ has *variance per evaluation*
$v = m\,\sigma^2_m$; spending the remaining $n$ evaluations on it gives
variance about $v/n$, at a cost proportional to $c\,n$ with $c$ its time per
evaluation, so the winner minimises $v \cdot c$.

The candidates:

- `"qmc"`: `QMC_REPLICAS` scrambled Sobol' nets of a power-of-two size
  (`pilot_qmc_points`, at most 1/16 of the budget), their spread giving
  $\sigma^2_m$. QMC's $v$ keeps falling as its nets grow: the pilot measures
  the rate from quarter to half to whole nets (the first $2^k$ points of a net
  are a net), $\sigma^2 \propto m^{-1-r}$ with $r \in [0, 1]$, and projects
  $v$ to the final net size at that rate (at most `MAX_NET_GROWTH` times the
  pilot's size: small nets show pre-asymptotic rates). The same points, each
  uniform, also give plain Monte Carlo's variance: when QMC beats it by
  `QMC_CLEAR_WIN` per evaluation, the integrand is smooth at this scale, no
  grid gains that much, and the grid is not trained. A pilot whose mean a
  handful of points carried (effective sample size below `MIN_PILOT_ESS`:
  a narrow peak) measured nothing. Values with a power-law tail (Pareto
  $\hat k > 0.2$: an unbounded integrand such as $x^{-1/2}$) keep QMC near
  plain MC's variance while its replicas' spread comes out small: there QMC is
  credited with plain MC's variance, never a clear win.
- `"adaptive"`: the VEGAS+ grid trained as `method="adaptive"` would train it
  (`jaxmc.fit.VegasPlus`, ten rounds on at most a quarter of the budget),
  $\sigma^2_m$ of its last round. A young grid's variance says little of the
  trained one's (measured after 3 and 10 rounds: from 10x worse, on a 16-D
  discontinuity, to 1000x better, on a 5-D posterior), so the grid is dropped
  after `SCREEN_ROUNDS` rounds only when, projected to the end of its training
  at the rate its variance fell from the first round to the third, it would
  still be `SCREEN_MARGIN` times costlier than a QMC pilot that measured the
  integrand (a young grid on the 8-D i-flow Gaussian was dropped at 80 against
  QMC's 18, then trained to 0.35); otherwise it trains in full
  and the choice is made on the trained grid. If the grid wins it goes on
  as `method="adaptive"` does after training (refining rounds, then with a
  tolerance a frozen stream); if QMC wins, the training was the price of knowing.

The times per evaluation $c$ are fixed ratios (`RELATIVE_COST`), not clock
readings, so `"auto"` is deterministic in `(key, n)`: the grid's map, its
training and the stratified allocation make a VEGAS+ evaluation of a cheap
integrand 4-7x dearer than a Sobol' point on a CPU (0.17 s against 0.04 s per
$10^6$ in 4-D, steady state), and about as dear for an integrand that costs
more than the map; 3 sits between. The pilot's evaluations count in the
result's `n` but not in its mean: the streamed estimate uses fresh randomness,
independent of the choice, so it stays unbiased.
"""
from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp

from .._box import to_box
from .._checks import is_concrete
from .._diagnostics import power_law_tail, tail_of
from .._integrand import evaluate, ratio
from .._points._sobol import sobol_scramble
from ..fit import Integrand, VegasPlus, run_adaptation
from ..proposals import Grid
from ._adaptive import grid_bins
from ._stream import QMC_REPLICAS, final_net, replica_points


CANDIDATES = ("qmc", "adaptive")
PILOT_SHARE = 1 / 16  # at most this share of the budget on the QMC pilot
RELATIVE_COST = {"qmc": 1.0, "adaptive": 3.0}  # time per evaluation, relative to a Sobol' point
QMC_CLEAR_WIN = 1000.0  # QMC's pilot gain over plain MC beyond which no grid is tried
SCREEN_ROUNDS = 3  # VEGAS+ rounds before the grid may be dropped without full training
SCREEN_MARGIN = 10.0  # a young grid this much costlier than QMC is not trained on
MIN_PILOT_ESS = 32.0  # fewer effective QMC pilot samples than this measure nothing
MAX_NET_GROWTH = 8  # most the projection lets QMC's nets grow beyond the pilot's (its rate is pre-asymptotic)


class Pilot(eqx.Module):
    """What the pilot of `integrate(method="auto")` measured.

    **Fields:**

    - `candidates`: the methods tried, in order.
    - `variance_per_evaluation`: each one's $m \\sigma^2_m$ (for an array-valued
      integrand, summed over the components, relative to the squared mean).
    - `cost`: `variance_per_evaluation` times the relative time per evaluation.
    - `choice`: index of the winner in `candidates`.
    - `evaluations`: integrand evaluations the pilot spent, per candidate.
    """

    candidates: tuple[str, ...] = eqx.field(static=True)
    variance_per_evaluation: jax.Array
    cost: jax.Array
    choice: jax.Array
    evaluations: tuple[int, ...] = eqx.field(static=True)


def pilot_qmc_points(budget: int) -> int:
    """Points per replica of the QMC pilot: a power of two, 64 to 4096, within `PILOT_SHARE`."""
    share = max(budget * PILOT_SHARE / QMC_REPLICAS, 1)
    return min(max(1 << int(math.floor(math.log2(share))), 64), 4096)


def _relative_variance(mean, variance) -> jax.Array:
    """Variance scaled by the squared mean (summed over components); scale-free."""
    mean2 = jnp.maximum(mean**2, jnp.finfo(mean.dtype).tiny)
    return jnp.sum(jnp.where(mean != 0, variance / mean2, variance))


class _QMCPilot(eqx.Module):
    variance: jax.Array  # projected variance per evaluation (relative)
    clear_win: jax.Array  # QMC beats plain MC on its points by QMC_CLEAR_WIN
    blind: jax.Array  # saw nothing, or too few effective points to measure anything


@eqx.filter_jit
def _qmc_pilot(key, lo, hi, *, f, per_replica, growth, batched):
    """`QMC_REPLICAS` scrambled Sobol' nets of `per_replica` points, measured."""
    d = 1 if lo.ndim == 0 else lo.shape[0]
    volume = jnp.prod(hi - lo)

    def replica(k):
        u = replica_points(sobol_scramble(k, d), 0, per_replica.bit_length() - 1, lo.dtype)
        y, _ = ratio(evaluate(f, to_box(u if lo.ndim else u[:, 0], lo, hi), batched), 1 / volume)
        return y

    y = jax.vmap(replica)(jax.random.split(key, QMC_REPLICAS))

    def relative_variance_per_evaluation(values):
        means = jnp.mean(values, axis=1)
        variance = jnp.var(means, axis=0, ddof=1) / QMC_REPLICAS
        return _relative_variance(jnp.mean(means, axis=0), variance) * values.shape[0] * values.shape[1]

    full = relative_variance_per_evaluation(y)
    # The first half (quarter) of a net is a net: the rate between sizes, measured twice.
    half = relative_variance_per_evaluation(y[:, : per_replica // 2])
    quarter = relative_variance_per_evaluation(y[:, : per_replica // 4])
    flat = jnp.reshape(y, (-1,) + y.shape[2:])
    mean = jnp.mean(flat, axis=0)
    plain = _relative_variance(mean, jnp.var(flat, axis=0, ddof=1))
    # Effective sample size (sum |y|)^2 / sum y^2: ~1 when a single point hit a peak.
    tiny = jnp.finfo(flat.dtype).tiny
    ess = jnp.min(jnp.sum(jnp.abs(flat), axis=0) ** 2 / jnp.maximum(jnp.sum(flat**2, axis=0), tiny))
    measured = ess >= MIN_PILOT_ESS
    # QMC's variance per evaluation keeps falling as its nets grow, at the rate the pilot
    # shows from quarter to half and half to whole nets (the smaller of the two: each is
    # a ratio of 8-replica variances, noisy): n^-(1+r) per replica, r in [0, 1], 0 being
    # plain MC's rate.
    rate = jnp.clip(jnp.minimum(jnp.log2(quarter / half), jnp.log2(half / full)), 0.0, 1.0)
    rate = jnp.where(jnp.isfinite(rate), rate, 0.0)
    projected = full * jnp.asarray(growth, full.dtype) ** -rate
    # An unbounded integrand (a power-law tail of the values, k-hat > 0.2) keeps QMC's
    # variance near plain MC's and makes the replicas' spread skewed and small (the bound of
    # `bounded_variance`): QMC is credited with plain MC's variance there, and no clear win.
    heavy = jnp.any(power_law_tail(tail_of(flat)))
    projected = jnp.where(heavy, jnp.maximum(projected, plain), projected)
    blind = jnp.all(mean == 0) | ~measured
    return _QMCPilot(projected, (plain >= QMC_CLEAR_WIN * full) & measured & ~heavy, blind)


@eqx.filter_jit
def _grid_rounds(key, grid, *, f, rounds, round_size, batched):
    """`rounds` VEGAS+ rounds from `grid`: the first and last rounds' relative variance
    per evaluation, whether the last saw only zeros, and the trained state."""
    parts, state, _ = run_adaptation(
        VegasPlus(), key, Integrand(f, batched), grid, rounds, round_size
    )
    v_first, v_last = (
        _relative_variance(parts.mean[i], parts.variance[i]) * round_size for i in (0, -1)
    )
    return v_first, v_last, jnp.all(parts.mean[-1] == 0), state


def _projected(v_first, v_last, rounds_done: int, rounds: int):
    """The grid's variance per evaluation after `rounds`, if it kept falling at the rate
    its first `rounds_done` rounds showed (that fall taken as at most 1000-fold, never a rise)."""
    fall = jnp.where(v_first > 0, v_last / jnp.where(v_first > 0, v_first, 1.0), 1.0)
    fall = jnp.clip(jnp.where(jnp.isfinite(fall), fall, 1.0), 1e-3, 1.0)
    return v_last * fall ** ((rounds - rounds_done) / max(rounds_done - 1, 1))


def _choose(qmc: _QMCPilot, v_grid, grid_blind):
    """`(variance, cost, choice)` of the two candidates."""
    variance = jnp.stack([qmc.variance, v_grid])
    # A pilot that saw only zeros (a peak its points missed), or whose mean a handful of
    # points carried, measured nothing: it never beats one that measured the integrand.
    # If neither did, the grid, which kept looking as it trained, is the better bet.
    blind = jnp.stack([qmc.blind, grid_blind])
    variance = jnp.where(blind & ~jnp.all(blind), jnp.inf, variance)
    cost = variance * jnp.asarray([RELATIVE_COST[c] for c in CANDIDATES], variance.dtype)
    choice = jnp.where(qmc.clear_win, 0, jnp.where(jnp.all(blind), 1, jnp.argmin(cost)))
    return variance, cost, choice.astype(jnp.int32)


def run_pilot(key, f, lo, hi, budget, batched, rounds, round_size):
    """Run the candidates' pilots; returns `(Pilot, trained VEGAS+ state or None)`.

    The grid trains in two stages, `SCREEN_ROUNDS` rounds and then the rest of the
    `rounds` rounds of `round_size` that `method="adaptive"` trains for: a young
    grid's variance says little of the trained one's (measured after 3 and 10
    rounds: from 10x worse, on a 16-D discontinuity, to 1000x better, on a 5-D
    posterior), so the choice is made on the trained grid unless the young one,
    projected at the rate it was falling, is `SCREEN_MARGIN` times costlier than QMC.
    When QMC's pilot beats plain Monte Carlo on the same points by `QMC_CLEAR_WIN` per evaluation (a smooth integrand) no
    grid is trained at all. Both shortcuts are taken outside `jit` only, where the
    figures are known.
    """
    per_replica = pilot_qmc_points(budget)
    qmc_n = per_replica * QMC_REPLICAS
    key_qmc, key_screen, key_train = jax.random.split(key, 3)
    growth = min(final_net(budget - qmc_n) / per_replica, MAX_NET_GROWTH)
    qmc = _qmc_pilot(key_qmc, lo, hi, f=f, per_replica=per_replica, growth=growth, batched=batched)
    if is_concrete(qmc.clear_win) and bool(qmc.clear_win):
        return Pilot(("qmc",), qmc.variance[None], qmc.variance[None], jnp.asarray(0, jnp.int32), (qmc_n,)), None
    screen = min(SCREEN_ROUNDS, rounds)
    v_first, v_grid, grid_blind, state = _grid_rounds(
        key_screen, Grid(lo, hi, bins=grid_bins(round_size)), f=f, rounds=screen,
        round_size=round_size,
        batched=batched,
    )
    variance, cost, choice = _choose(qmc, v_grid, grid_blind)
    # Dropped only if, still falling at the rate its first rounds showed, the grid would
    # end SCREEN_MARGIN times costlier than QMC (a young grid on a peak is 100x off).
    prospect = _projected(v_first, v_grid, screen, rounds) * RELATIVE_COST["adaptive"]
    decided = (prospect > SCREEN_MARGIN * cost[0]) & ~qmc.blind
    if not (is_concrete(decided) and bool(decided)) and rounds > screen:
        _, v_grid, grid_blind, state = _grid_rounds(
            key_train, state.grid, f=f, rounds=rounds - screen, round_size=round_size,
            batched=batched,
        )
        trained = _choose(qmc, v_grid, grid_blind)
        variance, cost, choice = (jnp.where(decided, a, b) for a, b in zip((variance, cost, choice), trained))
    else:
        rounds = screen
    return Pilot(CANDIDATES, variance, cost, choice, (qmc_n, rounds * round_size)), state
