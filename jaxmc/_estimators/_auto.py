r"""`integrate(method="auto")`: a pilot that measures the candidates and picks the cheapest.

The figure of merit is the cost of a unit of variance. A method whose estimate
from $m$ evaluations has variance $\sigma^2_m$ has *variance per evaluation*
$v = m\,\sigma^2_m$; spending the remaining $n$ evaluations on it gives
variance about $v/n$, at a cost proportional to $c\,n$ with $c$ its time per
evaluation, so the winner minimises $v \cdot c$. For the candidates here
$v$ only overstates the final variance — randomised QMC and VEGAS+
stratification improve faster than $1/n$, and the grid keeps adapting — so the
comparison errs on no side in particular.

Candidates, each on a small share of the budget:

- `"qmc"`: `QMC_REPLICAS` scrambled Sobol' nets of a power-of-two size
  (`pilot_sizes`), their spread giving $\sigma^2_m$. The same points, each
  uniform, also give plain Monte Carlo's variance; when QMC beats it by
  `QMC_CLEAR_WIN` per evaluation the integrand is smooth at this scale and the
  grid is not tried (a grid gains far less than that on a smooth integrand).
- `"adaptive"`: `PILOT_ROUNDS` rounds of VEGAS+ from a uniform grid
  (`jaxmc.fit.VegasPlus`), $\sigma^2_m$ of the last round. If it wins, the grid
  trains on from there; since the pilot's grid is young, its figure is
  projected over the rounds still to come at the pilot's own geometric rate of
  improvement $(v_3/v_1)^{1/2}$ per round (clipped to $[0.1, 1]$, at most
  `MAX_TRAINING_GAIN` in all).

The times per evaluation $c$ are fixed ratios (`RELATIVE_COST`), not clock
readings, so `"auto"` is deterministic in `(key, n)`: the grid's map, its
training and the stratified allocation make a VEGAS+ evaluation of a cheap
4-D integrand about 4x dearer than a Sobol' point on a CPU (0.17 s against
0.04 s per $10^6$ in steady state), and about as dear for an integrand that
costs more than the map; 3 sits between. The pilot's evaluations count in the result's `n` but not in its
mean: the streamed estimate uses fresh randomness, independent of the choice,
so it stays unbiased.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp

from .._box import to_box
from .._checks import is_concrete
from .._integrand import evaluate, ratio
from .._points._common import uint32_to_unit
from .._points._sobol import sobol_block, sobol_scramble
from ..fit import Integrand, VegasPlus, run_adaptation as _run_adaptation
from ..proposals import Grid
from ..stats import Estimate
from ._stream import QMC_REPLICAS


# Compiled once per integrand and sizes (eagerly, a scan would be traced on every call).
run_adaptation = eqx.filter_jit(_run_adaptation)

CANDIDATES = ("qmc", "adaptive")
PILOT_ROUNDS = 3  # VEGAS+ rounds in the pilot
PILOT_SHARE = 1 / 16  # at most this share of the budget on each candidate's pilot
RELATIVE_COST = {"qmc": 1.0, "adaptive": 3.0}  # time per evaluation, relative to a Sobol' point
GRID_BINS = 64  # grid bins per axis for the VEGAS+ candidate
QMC_CLEAR_WIN = 1000.0  # QMC's pilot gain over plain MC beyond which no grid is tried
MAX_TRAINING_GAIN = 1000.0  # most the projection credits the grid's further training


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


def pilot_sizes(budget: int) -> tuple[int, int]:
    """`(points per QMC replica, points per VEGAS+ round)`, powers of two within `PILOT_SHARE`."""
    share = max(budget * PILOT_SHARE, 1)
    qmc = 1 << int(math.floor(math.log2(max(share / QMC_REPLICAS, 1))))
    rounds = 1 << int(math.floor(math.log2(max(share / PILOT_ROUNDS, 1))))
    return min(max(qmc, 64), 4096), min(max(rounds, 256), 1 << 14)


def _relative_variance(est) -> jax.Array:
    """Variance scaled by the squared mean (summed over components); scale-free."""
    mean2 = jnp.maximum(est.mean**2, jnp.finfo(est.mean.dtype).tiny)
    return jnp.sum(jnp.where(est.mean != 0, est.variance / mean2, est.variance))


@eqx.filter_jit
def _qmc_pilot(key, lo, hi, *, f, per_replica, batched):
    """`QMC_REPLICAS` scrambled Sobol' nets of `per_replica` points: the QMC `Estimate`
    and the plain-MC variance per evaluation of the same points (each is uniform)."""
    d = 1 if lo.ndim == 0 else lo.shape[0]
    volume = jnp.prod(hi - lo)

    def replica(k):
        directions, shift = sobol_scramble(k, d)
        u = uint32_to_unit(sobol_block(directions, shift, 0, per_replica.bit_length() - 1), lo.dtype)
        y, bad = ratio(evaluate(f, to_box(u if lo.ndim else u[:, 0], lo, hi), batched), 1 / volume)
        return y, jnp.sum(bad, dtype=jnp.int32)

    y, bad = jax.vmap(replica)(jax.random.split(key, QMC_REPLICAS))
    means = jnp.mean(y, axis=1)
    mean = jnp.mean(means, axis=0)
    variance = jnp.var(means, axis=0, ddof=1) / QMC_REPLICAS
    n = jnp.asarray(QMC_REPLICAS * per_replica, jnp.int32)
    plain = jnp.var(jnp.reshape(y, (-1,) + y.shape[2:]), axis=0, ddof=1)
    return Estimate(mean, variance, n, jnp.sum(bad)), Estimate(mean, plain, n, jnp.sum(bad))


def run_pilot(key, f, lo, hi, budget, batched, training_rounds):
    """Run the candidates' pilots; returns `(Pilot, VEGAS+ state or None)`.

    `training_rounds`: the VEGAS+ rounds the grid would train for in all if chosen.
    When QMC's pilot already beats plain Monte Carlo on the same points by
    `QMC_CLEAR_WIN` per evaluation (a smooth integrand), no grid could win and its
    pilot is skipped (outside `jit`, where the figures are known).
    """
    per_replica, round_size = pilot_sizes(budget)
    qmc_n = per_replica * QMC_REPLICAS
    key_qmc, key_grid = jax.random.split(key)
    qmc, plain = _qmc_pilot(key_qmc, lo, hi, f=f, per_replica=per_replica, batched=batched)
    v_qmc = _relative_variance(qmc) * qmc_n
    clear_win = (_relative_variance(plain) >= QMC_CLEAR_WIN * v_qmc) & jnp.any(qmc.mean != 0)
    if is_concrete(clear_win) and bool(clear_win):
        return Pilot(("qmc",), v_qmc[None], v_qmc[None], jnp.asarray(0), (qmc_n,)), None
    parts, state, _ = run_adaptation(
        VegasPlus(), key_grid, Integrand(f, batched), Grid(lo, hi, bins=GRID_BINS), PILOT_ROUNDS,
        round_size,
    )
    first, last = (jax.tree.map(lambda a: a[i], parts) for i in (0, -1))
    # The grid keeps training if chosen: credit it the pilot's improvement per round for
    # the rounds still to come, at most MAX_TRAINING_GAIN in all (measured gains from round
    # 3 to 10: 8x on a smooth product, 30x on a 4-D peak, 200-3000x on a 5-D posterior).
    v_first, v_last = _relative_variance(first), _relative_variance(last)
    per_round = jnp.clip((v_last / v_first) ** (1 / (PILOT_ROUNDS - 1)), 0.1, 1.0)
    per_round = jnp.where(jnp.isfinite(per_round), per_round, 1.0)
    gain = jnp.maximum(per_round ** max(training_rounds - PILOT_ROUNDS, 0), 1 / MAX_TRAINING_GAIN)
    variance = jnp.stack([v_qmc, v_last * gain * round_size])
    # A pilot that saw only zeros measured nothing (a peak its points missed): it never
    # beats one that saw the integrand.
    blind = jnp.stack([jnp.all(qmc.mean == 0), jnp.all(last.mean == 0)])
    variance = jnp.where(blind & ~jnp.all(blind), jnp.inf, variance)
    cost = variance * jnp.asarray([RELATIVE_COST[c] for c in CANDIDATES], variance.dtype)
    choice = jnp.where(clear_win, 0, jnp.argmin(cost))
    pilot = Pilot(CANDIDATES, variance, cost, choice, (qmc_n, PILOT_ROUNDS * round_size))
    return pilot, state
