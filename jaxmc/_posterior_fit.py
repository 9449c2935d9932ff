r"""`expectation`'s fitting stage: a VEGAS+ grid trained on $\pi$, then a mixture of
Gaussians fitted to its weighted points (population Monte Carlo), each with its figure of
merit, the relative variance of the evidence per evaluation in its last round."""

from __future__ import annotations

import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from ._box import to_box
from ._integrand import evaluate
from ._stats import scatter_bound
from .fit import Integrand, VegasPlus
from .proposals import GaussianMixture, Grid


GRID_BINS = 64  # bins per axis of the VEGAS+ grid
PILOT = 256  # uniform points that set the first scale of pi
MAX_ROUNDS = 10  # VEGAS+ training rounds (at most), on at most a quarter of the budget
COMPONENTS = 16  # Gaussians in the mixture
MIXTURE_ROUNDS = 3  # mixture rounds: fit to the previous round's weighted samples, draw a round
# The mixture's scales are widened by WIDEN and a broad Gaussian (BROAD times the samples'
# spread) gets weight DEFENSIVE: q's tails are heavier than pi's, so the weights stay bounded
# and the error bars honest (the values chosen on the project's benchmarks).
WIDEN = 1.4
BROAD = 3.0
DEFENSIVE = 0.1
# The grid trains on exp(log pi - c), c the largest log pi seen, capped at exp(CAP) while c
# catches up (squares stay finite in float32).
CAP = 20.0
# Standard deviations (of its logarithm) at which the rounds' scatter bounds the grid's figure.
SCATTER_SIGMAS = 2.0


class Plan(NamedTuple):
    """Static sizes: points per round, VEGAS+ rounds, mixture rounds, final points."""

    block: int
    rounds: int
    mixture_rounds: int
    final: int


def plan_for(n: int, method: str) -> Plan:
    """The sizes for `n` evaluations (at least `expectation`'s minimum) and `method`."""
    # Rounds of about n/40 points, a power of two from 256 to 2^14, as `integrate`'s VEGAS+.
    block = min(1 << 14, max(256, 1 << int(math.floor(math.log2(n // 40)))))
    rounds = max(2, min(MAX_ROUNDS, n // (4 * block)))
    mixture_rounds = 0 if method == "grid" else MIXTURE_ROUNDS
    final = n - PILOT - (rounds + mixture_rounds) * block
    assert final >= block  # (n >= `expectation`'s MIN_N): at least one round's allocation to repeat
    return Plan(block, rounds, mixture_rounds, final)


class Fitted(eqx.Module):
    """What the fitting stage hands to the final one."""

    grid: Grid
    counts: jax.Array  # (H,) points per VEGAS+ hypercube of a round of `block` points
    mixture: GaussianMixture | None
    relative_variance: jax.Array  # (2,) per evaluation, of the evidence: grid, mixture


def log_pi(log_density, x, batched, dtype) -> jax.Array:
    r"""$\log\pi$ at the points `x` `(m, ...)`, in `dtype`."""
    return evaluate(log_density, x, batched, "log_density").astype(dtype)


def _defensive(mixture: GaussianMixture, x: jax.Array, weights: jax.Array) -> GaussianMixture:
    """`mixture`'s scales widened by `WIDEN`, plus a Gaussian of weight `DEFENSIVE` at the
    weighted mean of the samples `x` with `BROAD` times their spread along each axis."""
    x = jnp.reshape(x, (x.shape[0], -1))
    centre = jnp.sum(weights[:, None] * x, axis=0)
    spread = jnp.sqrt(jnp.sum(weights[:, None] * (x - centre) ** 2, axis=0))
    scale = jnp.maximum(BROAD * spread, 0.01 * jnp.reshape(mixture.hi - mixture.lo, (-1,)))
    log_w = jax.nn.log_softmax(mixture.logits) + math.log(1 - DEFENSIVE)
    return eqx.tree_at(
        lambda m: (m.logits, m.means, m.log_scales),
        mixture,
        (jnp.append(log_w, math.log(DEFENSIVE)), jnp.concatenate([mixture.means, centre[None]]),
         jnp.concatenate([mixture.log_scales + math.log(WIDEN), jnp.log(scale)[None]])),
    )


def weights_of(log_pi: jax.Array, log_q: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    r"""Weights $\pi/q$ scaled by $e^{-c}$, $c = \max\log(\pi/q)$: `(w, c, bad)`.

    A NaN or $+\infty$ log weight is an error (`bad`, weight 0); $-\infty$ is a zero weight.
    """
    log_w = log_pi - log_q
    bad = jnp.isnan(log_w) | (log_w == jnp.inf)
    log_w = jnp.where(bad, -jnp.inf, log_w)
    top = jax.lax.stop_gradient(jnp.max(log_w))
    top = jnp.where(jnp.isfinite(top), top, 0.0)
    return jnp.exp(log_w - top), top, bad


def fit(key, log_density, lo, hi, *, plan: Plan, batched: bool) -> Fitted:
    """The pilot and the VEGAS+ training, then (if `plan.mixture_rounds`) the mixture's rounds.

    Two compiled stages, so that every method shares the grid's."""
    key_grid, key_mixture = jax.random.split(key)
    grid, counts, grid_rv, x, weights = _train_grid(
        key_grid, log_density, lo, hi, block=plan.block, rounds=plan.rounds, batched=batched
    )
    if not plan.mixture_rounds:
        return Fitted(grid, counts, None, jnp.stack([grid_rv, jnp.full_like(grid_rv, jnp.inf)]))
    mixture, mixture_rv = _fit_mixture(
        key_mixture, log_density, x, weights, lo, hi, block=plan.block,
        rounds=plan.mixture_rounds, batched=batched,
    )
    return Fitted(grid, counts, mixture, jnp.stack([grid_rv, mixture_rv]))


@eqx.filter_jit
def _train_grid(key, log_density, lo, hi, *, block: int, rounds: int, batched: bool):
    """The pilot and `rounds` VEGAS+ rounds: the grid, its last allocation, the last round's
    relative variance of the evidence per evaluation, and its points with their weights."""
    dtype = lo.dtype
    key_pilot, key_grid = jax.random.split(key)
    u = jax.random.uniform(key_pilot, (PILOT,) + lo.shape, dtype)
    lp = log_pi(log_density, to_box(u, lo, hi), batched, dtype)
    scale = jnp.max(jnp.where(jnp.isnan(lp), -jnp.inf, lp))
    scale = jnp.where(jnp.isfinite(scale), scale, 0.0)

    rule = VegasPlus()
    state = rule.init(key_grid, Grid(lo, hi, bins=GRID_BINS), block)
    carry, static = eqx.partition(state, eqx.is_array)

    def round_(carry, index):
        state, scale, _ = carry
        # pi scaled by the largest value seen so far (capped while the scale catches up).
        f = lambda x: jnp.exp(jnp.minimum(jnp.asarray(log_density(x), dtype) - scale, CAP))  # noqa: E731
        state, est, samples = rule.step(key_grid, index, eqx.combine(state, static), Integrand(f, batched))
        seen = scale + jnp.log(jnp.max(samples.fx))
        seen_scale = jnp.where(jnp.isfinite(seen), jnp.maximum(scale, seen), scale)
        # Only what is used is carried (the round's other diagnostics are then never computed).
        last = (est.mean, est.variance, samples.x, samples.importance_weights())
        # (Each round's evidence on one scale, for the rounds' scatter.)
        return (eqx.partition(state, eqx.is_array)[0], seen_scale, last), jnp.log(est.mean) + scale

    # The last round's figures and samples are carried (one trace of the round).
    shapes = jax.eval_shape(lambda: round_((carry, scale, None), 0)[0][2])
    empty = jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), shapes)
    (carry, _, last), log_means = jax.lax.scan(round_, (carry, scale, empty), jnp.arange(rounds))
    mean, variance, x, weights = last
    state = eqx.combine(carry, static)
    mean2 = jnp.maximum(mean**2, jnp.finfo(dtype).tiny)
    relative_variance = jnp.where(mean > 0, variance * block / mean2, jnp.inf)
    # The last round's variance comes from pairs of points in hypercubes, which a hypercube
    # the grid has not yet resolved inflates: it is kept at most at the rounds' scatter's
    # pessimistic bound, as `auto` reads a trained grid.
    scatter = scatter_bound(jnp.exp(log_means - log_means[-1]), block, SCATTER_SIGMAS)
    relative_variance = jnp.minimum(relative_variance, scatter)
    return state.grid, state.draw.counts, relative_variance, x, weights


@eqx.filter_jit
def _fit_mixture(key, log_density, x, weights, lo, hi, *, block: int, rounds: int, batched: bool):
    """Mixture rounds: fit to the previous round's weighted samples (the grid's first), draw
    a round from the fitted mixture. The last round measures the final mixture: returns it
    and its relative variance of the evidence per evaluation."""
    dtype = lo.dtype
    components = min(COMPONENTS, block)

    def refit(carry, index):
        x, weights = carry
        q = _defensive(GaussianMixture.from_samples(x, weights, lo, hi, components,
                                                    until_noise=True), x, weights)
        x, _ = q.sample(jax.random.fold_in(key, index), block)
        w, _, _ = weights_of(log_pi(log_density, x, batched, dtype), q.log_pdf(x))
        mean = jnp.mean(w)  # > 0: the largest weight is 1 unless all are 0
        relative_variance = jnp.where(mean > 0, jnp.var(w) / jnp.where(mean > 0, mean, 1) ** 2, jnp.inf)
        return (x, w / jnp.where(mean > 0, jnp.sum(w), 1)), (q, relative_variance)

    _, (mixtures, rvs) = jax.lax.scan(refit, (x, weights), jnp.arange(rounds))
    return jax.tree.map(lambda a: a[-1], mixtures), rvs[-1]
