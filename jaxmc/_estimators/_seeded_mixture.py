r"""`integrate(method="auto")`'s mixture: Gaussians seeded from a trained grid, then adapted.

The mixture is fitted by EM (`GaussianMixture.from_samples`) to importance-weighted
points of the integrand, weights $|f|/q$ for points drawn from $q$, and mixed with
the trained grid at `DEFENSIVE_SHARE` (defensive importance sampling, Hesterberg
1995: its values are bounded wherever the grid's are). It is seeded from the grid's
last training round (`seeded_mixture`); once it has won the pilot it is refitted to
points drawn from itself (`adapted_mixture`), as population Monte Carlo does (Cappé
et al. 2004): the grid's points are a product of axis densities, dense where the
axes' marginals are, not where the integrand is, and a mixture's own points sit
on its peaks.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp

from .._integrand import evaluate, ratio
from ..proposals import GaussianMixture, Grid, Mixture


MIXTURE_COMPONENTS = 8  # Gaussians in the mixture seeded from the grid
DEFENSIVE_SHARE = 0.1  # the trained grid's share of the mixture
# EM iterations seeding the mixture. 20 fitted as well as 50 (4 keys each of vegas's 4-D
# Gaussian, i-flow's camels, the 5-D posterior), and 10 as well as 20: the mixture's
# variance per evaluation, on 8x the pilot's points, 6 keys each of those, i-flow's 8-D
# Gaussian and two 4-D Gaussians (and the 10-D ball at 1e6), had geometric means within
# 10% at 1e5 and 1e6; 5 left a posterior key unfitted. An EM step costs ~0.12 ms on
# 2048 points in 4-D, ~0.24 ms on 4096 in 8-D (the exponentials of the responsibilities).
MIXTURE_EM_ITERATIONS = 10
MIXTURE_FIT_POINTS = 4096  # at most this many of the grid's points seed the mixture
# The winning mixture's refit: on about a tenth of what the pilot left (a power of two,
# at most ADAPT_MAX_POINTS), EM on at most ADAPT_FIT_POINTS of them (~11 ms in 4-D on a
# CPU; see `adapted_mixture` for what 2^13 cost).
ADAPT_SHARE = 10
ADAPT_MAX_POINTS = 1 << 16
ADAPT_FIT_POINTS = 1 << 14


def _fitted_gaussians(grid: Grid, x, weights) -> tuple[GaussianMixture, jax.Array]:
    """`MIXTURE_COMPONENTS` Gaussians fitted by EM to points `x` of `weights` (non-finite
    ones count as zero) in `grid`'s box; and whether any weight was positive (if none,
    even weights keep EM finite and the fit says nothing)."""
    weights = jnp.where(jnp.isfinite(weights), weights, 0)
    seen = jnp.sum(weights) > 0
    weights = jnp.where(seen, weights, 1.0)
    gm = GaussianMixture.from_samples(x, weights / jnp.sum(weights), grid.lo, grid.hi,
                                      components=MIXTURE_COMPONENTS, iterations=MIXTURE_EM_ITERATIONS)
    return gm, seen


def _magnitude(values):
    """Each point's $|y|$, in quadrature over an array-valued integrand's components."""
    y = jnp.reshape(values, (values.shape[0], -1))
    return jnp.sqrt(jnp.sum(jnp.where(jnp.isfinite(y), y, 0) ** 2, axis=-1))


def seeded_mixture(grid: Grid, samples) -> Mixture:
    r"""The mixture fitted to a grid's round of `samples` (weights $|f|\,w/q$). At most
    `MIXTURE_FIT_POINTS` of them, a stride apart: a VEGAS+ round lies hypercube by
    hypercube, so the stride keeps every part of the cube, and EM's time grows with
    the points."""
    stride = max(1, samples.weights.shape[0] // MIXTURE_FIT_POINTS)
    samples = jax.tree.map(lambda a: a[::stride], samples)
    weights = _magnitude(samples.fx) * samples.weights * jnp.exp(-samples.log_q)
    gm, _ = _fitted_gaussians(grid, samples.x, weights)
    return Mixture((gm, grid), (1 - DEFENSIVE_SHARE, DEFENSIVE_SHARE), stratified=True)


def adaptation_points(rest: int) -> int:
    """Points the winning mixture draws to refit itself, out of the `rest` of the budget:
    about `rest / ADAPT_SHARE`, a power of two, at most `ADAPT_MAX_POINTS` (0 if under 256)."""
    size = min(ADAPT_MAX_POINTS, 1 << int(math.floor(math.log2(max(rest // ADAPT_SHARE, 1)))))
    return size if size >= 256 else 0


def _refit(mixture: Mixture, x, y) -> Mixture:
    """`mixture` refitted to its own draws `x` of values `y` (at most `ADAPT_FIT_POINTS` of
    them, a stride apart); unchanged if they were all zero."""
    stride = max(1, x.shape[0] // ADAPT_FIT_POINTS)
    gm, seen = _fitted_gaussians(mixture.proposals[1], x[::stride], _magnitude(y[::stride]))
    gm = jax.tree.map(lambda new, old: jnp.where(seen, new, old), gm, mixture.proposals[0])
    return eqx.tree_at(lambda m: m.proposals[0], mixture, gm)


@eqx.filter_jit
def adapted_mixture(key, mixture: Mixture, draws, *, f, size, batched) -> Mixture:
    r"""The winning mixture, refitted twice to its own weighted points (population Monte
    Carlo): to the pilot's `draws = (x, y)`, which cost nothing more, then to `size`
    points drawn from that refit.

    Measured (relative variance per evaluation on $2^{18}$ points, 4 keys, geometric
    mean; as seeded, then after the two refits), at $10^6$ ($2^{16}$ points): 5-D
    posterior 3.0 -> 0.45, i-flow's 16-D camel 4.4 -> 0.17, 10-D ball 42 -> 3.6,
    i-flow's 8-D Gaussian 0.020 -> 0.013, vegas's 4-D Gaussian 0.011 -> 0.012; at
    $10^5$ ($2^{12}$ points): camel 1.2 -> 0.13, ball 59 -> 3.8, i-flow's Gaussian
    0.036 -> 0.025, vegas's 0.023 -> 0.025, and the posterior's RMS error over 7
    keys halved. A refit on the pilot's points alone gained less (0.9 and 0.52 on the
    posterior and the camel at $10^6$), one from the seeded mixture's own $2^{16}$
    points erred once on the posterior (32 against 5.7), and EM on $2^{13}$ of the
    $2^{16}$ points left vegas's Gaussian at 0.016: the refit's parameters carry the
    noise of its points' effective sample size, which a mixture that already fits
    well feels.
    The `size` points are not in the estimate (as the pilot's): drawn from a mixture
    that fitted worse, they would weigh on it.

    Cost (the `auto` benchmark, whole calls that streamed from the mixture, float64 on a
    CPU): +5-17 ms at $10^5$ (30-45 ms before), +23-50 ms at $10^6$ (160-230 ms before),
    and ~3 s more in a first call (two EM fits, a draw from the mixture: 11-12 s to
    13-15 s). The posterior's efficiency ratio to the better of vegas and SciPy went
    0.04 -> 4.7 at $10^6$ and 8 -> 38 at $10^5$, the 10-D ball's and i-flow's 8-D
    Gaussian's 1.2 -> 2.1 and 2.3 -> 3.5 at $10^6$.
    """
    mixture = _refit(mixture, *draws)
    x, p = mixture.sample(key, size)
    y, _ = ratio(evaluate(f, x, batched), p)
    return _refit(mixture, x, y)
