r"""`fit`'s default for each proposal type: a density fitted to weighted samples, not a gradient fit.

A gradient solver on a sample average of the variance stalls on piecewise-constant
densities and, from a start that barely sees a narrow peak, drifts instead of
finding it. So by default `fit` first lets VEGAS find where $|f|$ is (rounds of
the VEGAS rule on a `Grid` over the proposal's box, Lepage 1978), then fits the
proposal to the grid's importance-weighted samples, the standard recipe of
adaptive importance sampling (population Monte Carlo: Cappé et al. 2008; flows
trained on weighted samples: Müller et al. 2019, Gao et al. 2020):

- `Grid`: the VEGAS rounds themselves, on the proposal's own grid.
- `Partition`: rounds of MISER-like growth (`PartitionGrowth`) instead.
- `GaussianMixture`, `PiecewiseLinear`: expectation-maximisation on the last
  round's samples $x_i$ with weights $w_i \propto |f(x_i)|/q(x_i)$ (their
  `from_samples`), which maximises $\sum_i w_i \log p(x_i)$, i.e. minimises the
  forward KL divergence $D(p_f \| p)$ to $p_f = |f|/I$ -- whose minimiser over
  all densities, $p_f$, is the zero-variance density.
- `Flow`: Adam on the same forward KL, on a fresh batch from the final grid
  at every step (the grid is fixed and positive on the whole box, so no region
  is starved while the flow learns).
- `Mixture`: each component as it would be fitted alone (fixed weights stay).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
import optimistix as optx

from ..proposals import (
    Flow,
    GaussianMixture,
    Grid,
    Mixture,
    Partition,
    PiecewiseLinear,
    weighted_draw,
)
from ._miser import PartitionGrowth
from ._objectives import log_abs, objective_loss
from ._rule import Integrand, Samples, run_adaptation
from ._solvers import run_steps, split_parameters
from ._vegas import Vegas


# Rounds of the VEGAS rule (or of partition growth) the defaults run: the grid settles
# in a handful (vegas's own examples train for about ten).
ADAPT_ROUNDS = 10
# Bins per axis of the grid that finds |f| for the other proposals (vegas's default is 1000
# over all axes; 64 per axis resolves features to ~1/64 of the box with small rounds).
_WARM_START_BINS = 64
# Adam's learning rate for a flow's forward-KL training: maximum weighted likelihood on
# fresh batches is well conditioned, so a larger step than for the variance (3e-3) is safe.
_FLOW_KL_LEARNING_RATE = 1e-2


def has_default_fit(proposal: Any, n: int) -> bool:
    """Whether `fit`'s default for `proposal` is one of this module's fits (else a gradient fit)."""
    if isinstance(proposal, Partition):
        return n >= 4 * proposal.max_cells
    if isinstance(proposal, (Grid, GaussianMixture, PiecewiseLinear, Flow)):
        return True
    if isinstance(proposal, Mixture):
        parts = [p for p in proposal.proposals if _has_parameters(p)]
        return bool(parts) and all(has_default_fit(p, n) for p in parts)
    return False


def _has_parameters(proposal: Any) -> bool:
    try:
        split_parameters(proposal, None)
    except ValueError:
        return False
    return True


def _second_moment(proposal, samples: Samples) -> jax.Array:
    r"""$\log E[(f/p)^2]$ of the fitted `proposal`, on a round's samples reweighted from their $q$."""
    log_p = proposal.log_pdf(samples.x)
    return objective_loss("variance", log_abs(samples.fx), log_p, samples.weights, samples.log_q)


def default_fit(key, integrand: Integrand, proposal: Any, n: int, max_steps: int):
    """`fit`'s default: `(proposal, loss, steps, losses)` (see the module docstring)."""
    rounds = min(max_steps, ADAPT_ROUNDS)
    if isinstance(proposal, Grid):
        _, state, samples = run_adaptation(
            Vegas(), key, integrand, proposal, rounds, n, keep_samples=True
        )
        loss = objective_loss("variance", log_abs(samples.fx), samples.log_q, samples.weights)
        return state.grid, loss, jnp.asarray(rounds), None
    if isinstance(proposal, Partition):
        _, state, samples = run_adaptation(
            PartitionGrowth(), key, integrand, proposal, rounds, n, keep_samples=True
        )
        return state.partition, _second_moment(state.partition, samples), jnp.asarray(rounds), None
    key_grid, key_fit = jax.random.split(key)
    grid = Grid(proposal.lo, proposal.hi, _WARM_START_BINS)
    _, state, samples = run_adaptation(
        Vegas(), key_grid, integrand, grid, rounds, n, keep_samples=True
    )
    fitted, flow_losses = _fit_to_grid(key_fit, integrand, proposal, state.grid, samples, n, max_steps)
    steps = rounds + (0 if flow_losses is None else max_steps)
    return fitted, _second_moment(fitted, samples), jnp.asarray(steps), flow_losses


def _fit_to_grid(key, integrand, proposal, grid, samples: Samples, n: int, max_steps: int):
    """Fit `proposal` to $|f|$ given VEGAS's final `grid` and its last round's `samples`."""
    weights = samples.importance_weights()
    lo, hi = proposal.lo, proposal.hi
    if isinstance(proposal, GaussianMixture):
        return GaussianMixture.from_samples(samples.x, weights, lo, hi, proposal.components), None
    if isinstance(proposal, PiecewiseLinear):
        return PiecewiseLinear.from_samples(samples.x, weights, lo, hi, proposal.bins), None
    if isinstance(proposal, Flow):
        return _flow_forward_kl(key, integrand, proposal, grid, n, max_steps)
    if isinstance(proposal, Mixture):
        keys = jax.random.split(key, len(proposal.proposals))
        parts, losses = [], None
        for k, p in zip(keys, proposal.proposals, strict=True):
            if not _has_parameters(p):
                parts.append(p)
                continue
            if isinstance(p, (Grid, Partition)):
                fitted, *_ = default_fit(k, integrand, p, n, max_steps)
            else:
                fitted, part_losses = _fit_to_grid(k, integrand, p, grid, samples, n, max_steps)
                losses = part_losses if losses is None else losses
            parts.append(fitted)
        return eqx.tree_at(lambda m: m.proposals, proposal, tuple(parts)), losses
    raise TypeError(f"No default fit for {type(proposal).__name__}.")  # has_default_fit guards


def _flow_forward_kl(key, integrand, flow, grid, n: int, steps: int):
    r"""`steps` Adam steps on $D(p_f \| p_\theta)$, each on a fresh batch of `n` from `grid`."""
    params, static = split_parameters(flow, None)

    def batch(i, _):
        x, log_q, w = weighted_draw(grid, jax.random.fold_in(key, i), n)
        return x, jax.lax.stop_gradient(log_abs(integrand(x))), log_q, w

    def loss(p, args):
        x, logf, log_q, w = args
        return objective_loss("kl", logf, eqx.combine(p, static).log_pdf(x), w, log_q)

    solver = optx.OptaxMinimiser(optax.adam(_FLOW_KL_LEARNING_RATE), rtol=0.0, atol=0.0)
    params, losses = run_steps(batch, loss, solver, params, steps)
    return eqx.combine(params, static), losses
