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
  (`pilot_qmc_points`), their spread giving $\sigma^2_m$.
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

from ..fit import Integrand, VegasPlus, run_adaptation as _run_adaptation
from ..proposals import Grid
from ._stream import QMC_REPLICAS, plan, stream


# Compiled once per integrand and sizes (eagerly, a scan would be traced on every call).
run_adaptation = eqx.filter_jit(_run_adaptation)

CANDIDATES = ("qmc", "adaptive")
PILOT_ROUNDS = 3  # VEGAS+ rounds in the pilot
PILOT_SHARE = 1 / 16  # at most this share of the budget on each candidate's pilot
RELATIVE_COST = {"qmc": 1.0, "adaptive": 3.0}  # time per evaluation, relative to a Sobol' point
GRID_BINS = 64  # grid bins per axis for the VEGAS+ candidate
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


def run_pilot(key, f, lo, hi, budget, mesh, batched, training_rounds):
    """Run every candidate's pilot; returns `(Pilot, VEGAS+ state)`.

    `training_rounds`: the VEGAS+ rounds the grid would train for in all if chosen.
    """
    per_replica, round_size = pilot_sizes(budget)
    qmc_n = per_replica * QMC_REPLICAS
    key_qmc, key_grid = jax.random.split(key)
    d = 1 if lo.ndim == 0 else lo.shape[0]
    zero = jnp.zeros((), lo.dtype)
    qmc = stream(
        key_qmc, None, lo, hi, zero, zero, f=f, plan=plan("qmc", qmc_n, qmc_n, mesh.devices.size, d),
        mesh=mesh, tolerant=False, progress=False, batched=batched,
    )
    rule = VegasPlus()
    parts, state, _ = run_adaptation(
        rule, key_grid, Integrand(f, batched), Grid(lo, hi, bins=GRID_BINS), PILOT_ROUNDS, round_size
    )
    first, last = (jax.tree.map(lambda a: a[i], parts) for i in (0, -1))
    # The grid keeps training if chosen: credit it the pilot's improvement per round for
    # the rounds still to come, at most MAX_TRAINING_GAIN in all (measured gains from round
    # 3 to 10: 8x on a smooth product, 30x on a 4-D peak, 200-3000x on a 5-D posterior).
    v_first, v_last = _relative_variance(first), _relative_variance(last)
    per_round = jnp.clip((v_last / v_first) ** (1 / (PILOT_ROUNDS - 1)), 0.1, 1.0)
    per_round = jnp.where(jnp.isfinite(per_round), per_round, 1.0)
    gain = jnp.maximum(per_round ** max(training_rounds - PILOT_ROUNDS, 0), 1 / MAX_TRAINING_GAIN)
    variance = jnp.stack([_relative_variance(qmc) * qmc_n, v_last * gain * round_size])
    # A pilot that saw only zeros measured nothing (a peak its points missed): it never
    # beats one that saw the integrand.
    blind = jnp.stack([jnp.all(qmc.mean == 0), jnp.all(last.mean == 0)])
    variance = jnp.where(blind & ~jnp.all(blind), jnp.inf, variance)
    cost = variance * jnp.asarray([RELATIVE_COST[c] for c in CANDIDATES], variance.dtype)
    pilot = Pilot(
        CANDIDATES, variance, cost, jnp.argmin(cost), (qmc_n, PILOT_ROUNDS * round_size)
    )
    return pilot, state
