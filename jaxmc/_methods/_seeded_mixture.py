r"""`integrate(method="auto")`'s mixture: Gaussians seeded from a trained grid, then adapted.

The mixture is fitted by EM (`GaussianMixture.from_samples`) to importance-weighted
points of the integrand, weights $|f|/q$ for points drawn from $q$, and mixed with
the trained grid at `DEFENSIVE_SHARE` (defensive importance sampling, Hesterberg
1995: its values are bounded wherever the grid's are); a wide Gaussian among the
fitted ones bounds them where the grid's are not (`_with_wide_gaussian`). It is
seeded from the grid's last training round (`seeded_mixture`); once it has won the
pilot it is refitted to points drawn from itself (`adapted_mixture`), as population
Monte Carlo does (Cappé et al. 2004): the grid's points are a product of axis
densities, dense where the axes' marginals are, not where the integrand is, and a
mixture's own points sit on its peaks.
"""

from __future__ import annotations

import math
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp

from .._compiled import per_integrand
from .._integrand import evaluate, ratio
from ..proposals import GaussianMixture, Grid, Mixture


MIXTURE_COMPONENTS = 8  # Gaussians in the mixture seeded from the grid
DEFENSIVE_SHARE = 0.1  # the trained grid's share of the mixture
# EM iterations seeding the mixture: more fit no better on the project's benchmarks,
# fewer could leave a fit unconverged, and each step costs time in proportion to its points
# (the exponentials of the responsibilities).
MIXTURE_EM_ITERATIONS = 10
MIXTURE_FIT_POINTS = 4096  # at most this many of the grid's points seed the mixture
# The winning mixture's refit: on about a tenth of what the pilot left (a power of two,
# at most ADAPT_MAX_POINTS), EM on at most ADAPT_FIT_POINTS of them (EM's time grows with
# its points; fewer fit noisier, see `adapted_mixture`).
ADAPT_SHARE = 10
ADAPT_MAX_POINTS = 1 << 16
ADAPT_FIT_POINTS = 1 << 14
# A wide Gaussian among the fitted ones (`_with_wide_gaussian`): its scale in the points'
# weighted standard deviations (and never below WIDE_MIN_SCALE of the box), its share in
# the seeded mixture (the pilot measures the fitted Gaussians) and in a refit (`_wide_share`).
WIDE_SCALE = 2.0
WIDE_MIN_SCALE = 0.01
WIDE_MIN_SHARE = 1e-3
WIDE_MAX_SHARE = 0.1


def _fitted_gaussians(grid: Grid, x, weights, wide_share=None) -> tuple[GaussianMixture, jax.Array]:
    """`MIXTURE_COMPONENTS` Gaussians fitted by EM to points `x` of `weights` (non-finite
    ones count as zero) in `grid`'s box, and a wide one (`_with_wide_gaussian`) at
    `wide_share`, or by the weights' spread if None (`_wide_share`); and whether any
    weight was positive (if none, even weights keep EM finite and the fit says nothing)."""
    weights = jnp.where(jnp.isfinite(weights), weights, 0)
    seen = jnp.sum(weights) > 0
    weights = jnp.where(seen, weights, 1.0)
    weights = weights / jnp.sum(weights)
    gm = GaussianMixture.from_samples(x, weights, grid.lo, grid.hi,
                                      components=MIXTURE_COMPONENTS, iterations=MIXTURE_EM_ITERATIONS)
    share = _wide_share(weights) if wide_share is None else wide_share
    return _with_wide_gaussian(gm, grid, x, weights, share), seen


def _with_wide_gaussian(gm: GaussianMixture, grid: Grid, x, weights, share) -> GaussianMixture:
    r"""`gm` with one more component at `share` of the weight: a Gaussian at the points'
    weighted mean, `WIDE_SCALE` times their weighted standard deviation on each axis.

    EM fits the Gaussians to what their points saw, and diagonal ones lie across a
    correlated peak: along the diagonal of a $d$-D Gaussian of equal correlations $\rho$,
    $f$ spreads as $\sigma\sqrt{1 + (d - 1)\rho}$, past the fitted parts, and where $q$
    falls faster than $f$ the weights $f/q$ have a heavy tail. The wide part bounds them:
    its variance on every axis, $4 s_j^2$, exceeds a Gaussian's along any direction of
    correlation up to $\rho = 3/(d - 1)$ ($0.75$ in 5-D).
    """
    mean = jnp.sum(weights[:, None] * x, axis=0)
    sd = jnp.sqrt(jnp.sum(weights[:, None] * (x - mean) ** 2, axis=0))
    width = grid.hi - grid.lo
    sd = jnp.clip(WIDE_SCALE * sd, WIDE_MIN_SCALE * width, width)
    logits = jax.nn.log_softmax(gm.logits) + jnp.log1p(-share)
    return eqx.tree_at(
        lambda g: (g.logits, g.means, g.log_scales), gm,
        (jnp.append(logits, jnp.log(share)), jnp.concatenate([gm.means, mean[None]]),
         jnp.concatenate([gm.log_scales, jnp.log(sd)[None]])),
    )


def _wide_share(weights):
    r"""The wide Gaussian's share in a refit: $v/8$ for points whose weights (normalised)
    have relative variance $v = m\sum_i w_i^2 - 1$, within [`WIDE_MIN_SHARE`,
    `WIDE_MAX_SHARE`].

    Where the Gaussians fit, a share $\alpha$ costs about $\alpha/(1-\alpha)$ in
    relative variance per evaluation (its points are wasted): for a fixed 0.1, many times
    a close fit's own. The points' spread measures how far the mixture they came from
    fits: heavy weights get the full share, a fit that is already close a small one.
    """
    v = weights.shape[0] * jnp.sum(weights**2) - 1
    return jnp.clip(v / 8, WIDE_MIN_SHARE, WIDE_MAX_SHARE)


def _magnitude(values):
    """Each point's $|y|$, in quadrature over an array-valued integrand's components."""
    y = jnp.reshape(values, (values.shape[0], -1))
    return jnp.sqrt(jnp.sum(jnp.where(jnp.isfinite(y), y, 0) ** 2, axis=-1))


def importance_weights(samples):
    r"""The unnormalised importance weights $|f(x_i)|\,w_i/q(x_i)$ of a round's `samples`:
    their sum estimates $\int |f|$."""
    return _magnitude(samples.fx) * samples.weights * jnp.exp(-samples.log_q)


def fit_points(samples):
    """The points of a grid's round of `samples` that seed the mixture: at most
    `MIXTURE_FIT_POINTS` of them, a stride apart (a VEGAS+ round lies hypercube by
    hypercube, so the stride keeps every part of the cube, and EM's time grows with
    the points)."""
    stride = max(1, samples.weights.shape[0] // MIXTURE_FIT_POINTS)
    return jax.tree.map(lambda a: a[::stride], samples)


def seeded_mixture(grid: Grid, samples) -> Mixture:
    r"""The mixture fitted to a grid's round of `samples` (weights $|f|\,w/q$), on its
    `fit_points`."""
    samples = fit_points(samples)
    gm, _ = _fitted_gaussians(grid, samples.x, importance_weights(samples), WIDE_MIN_SHARE)
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


@per_integrand
def mixture_values(x, p, *, f, batched):
    """The values $f/p$ at points `x` of density `p` (the one program of the mixture's fits
    compiled for each integrand; the rest serve every integrand of their shapes)."""
    return ratio(evaluate(f, x, batched), p)[0]


@partial(jax.jit, static_argnames="size")
def _refit_and_draw(key, mixture: Mixture, draws, *, size):
    mixture = _refit(mixture, *draws)
    return (mixture,) + mixture.sample(key, size)


_refit_jitted = jax.jit(_refit)


def adapted_mixture(key, mixture: Mixture, draws, *, f, size, batched) -> Mixture:
    r"""The winning mixture, refitted twice to its own weighted points (population Monte
    Carlo): to the pilot's `draws = (x, y)`, which cost nothing more, then to `size`
    points drawn from that refit.

    Two refits, the second on fresh points, move the Gaussians further onto the
    integrand than a refit on the pilot's points alone (chosen on the project's
    benchmarks). The refit's parameters carry the noise of its points' effective sample
    size, which a mixture that already fits well feels: hence EM on up to
    `ADAPT_FIT_POINTS` of them. The `size` points are not in the estimate (as the
    pilot's): drawn from a mixture that fitted worse, they would weigh on it. The fits
    and the draw are compiled once per shape; only the values (`mixture_values`) for each
    integrand. They cost two EM fits and a draw (and their compilation in a first call).
    """
    mixture, x, p = _refit_and_draw(key, mixture, draws, size=size)
    return _refit_jitted(mixture, x, mixture_values(x, p, f=f, batched=batched))
