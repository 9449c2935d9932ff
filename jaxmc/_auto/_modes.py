r"""Modes that auto's seeded mixture missed: found by ascent from the QMC pilot's best points.

A grid trained by VEGAS+ can lock onto one of several separated peaks (two Gaussians on
a diagonal, say): the grid and the mixture seeded from its points then hold one mode,
the estimate misses the other's mass by many standard errors, and the training rounds
are too noisy to object (vegas does the same). The QMC pilot's points, spread over the
whole box, lie on both sides: local ascent of $\log|f|$ from its best `MODE_STARTS` points
(`optimistix.BFGS`, in logit coordinates of the box, at most `MODE_STEPS` steps)
reaches the modes near them. A mode where the mixture puts far less density than
the integrand asks, $|f(m)| > $ `UNDERCOVERED` $\hat I\,q(m)$ ($\hat I$ the grid's
estimate, its largest weights capped: `_mixture.truncated_integral`), gets
a Gaussian of its own (Laplace's approximation: the covariance $H^{-1}$ of
$-\log|f|$ at $m$, its diagonal kept), at most `MODE_COMPONENTS` of them, one at
a time, each judged against the mixture with the ones before, each in place of
the fitted Gaussian of least weight.
Its share of the Gaussians is its Laplace mass against $\hat I$:
$Z/(\hat I + Z)$, $Z = |f(m)|\,(2\pi)^{d/2}\prod_j s_j$. A mode the grid
itself undercovers so (`grid_misses_a_mode`) tells `_auto` that the grid's
figure hides mass it does not sample.

Only an interior maximum counts (a positive definite $H$, finite values): a
singularity's ascent runs to the boundary, where $-\log|f|$ is concave; a flat
integrand (an indicator) has no gradient; a ridge has a singular $H$. An
integrand JAX cannot differentiate skips the search.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx

from .._integrand import evaluate
from ..proposals import Mixture


MODE_STARTS = 16  # the QMC pilot's best points the ascent starts from
MODE_STEPS = 32  # BFGS steps at most per start (each evaluates f and its gradient)
MODE_COMPONENTS = 2  # Gaussians added at modes, at most

# `optx.minimise` unwrapped from its `filter_jit`: the search always runs traced (inside
# the program compiled for the integrand), where that `jit` adds nothing but an entry in
# JAX's trace cache that holds the objective, and with it the integrand, for the life of
# the process.
_minimise = optx.minimise.__wrapped__
UNDERCOVERED = 10.0  # |f(m)| / (I q(m)) above which a mode gets a Gaussian of its own
MIN_SHARE, MAX_SHARE = 0.05, 0.5  # a new Gaussian's share of the Gaussians


def search_evaluations(d: int) -> int:
    """Integrand evaluations (with gradients) the search spends, at most: each start's
    steps, its value and its Hessian's `d` gradients."""
    return MODE_STARTS * (MODE_STEPS + 1 + d)


def differentiable(f, batched: bool, x) -> bool:
    """Whether JAX can differentiate $\\log|f|$ at a point like `x` `(d,)` (traced only)."""
    try:
        jax.eval_shape(jax.hessian(lambda p: _log_magnitude(f, batched, p)), x)
    except Exception:  # noqa: BLE001 (any failure to trace means: no search)
        return False
    return True


def _log_magnitude(f, batched, x):
    y = jnp.reshape(evaluate(f, x[None], batched)[0], (-1,))
    return 0.5 * jnp.log(jnp.sum(y**2))


def find_modes(f, batched, lo, hi, x, magnitude):
    r"""Ascent of $\log|f|$ from the `MODE_STARTS` points of `x` `(m, d)` with the largest
    `magnitude` `(m,)`: `(modes (S, d), |f| there (S,), Laplace scales (S, d), valid (S,))`."""
    width = hi - lo
    starts = x[jnp.argsort(-magnitude)[:MODE_STARTS]]

    def to_box(z):
        return lo + width * jax.nn.sigmoid(z)

    def ascend(x0):
        t = jnp.clip((x0 - lo) / width, 1e-6, 1 - 1e-6)
        z0 = jnp.log(t) - jnp.log1p(-t)
        objective = lambda z, _: -_log_magnitude(f, batched, to_box(z))  # noqa: E731
        solution = _minimise(objective, optx.BFGS(rtol=1e-5, atol=1e-5), z0,
                                 max_steps=MODE_STEPS, throw=False)
        mode = to_box(solution.value)
        log_f = _log_magnitude(f, batched, mode)
        hessian = jax.hessian(lambda p: -_log_magnitude(f, batched, p))(mode)
        cholesky = jnp.linalg.cholesky(hessian)
        covariance = jnp.linalg.inv(hessian)
        scale = jnp.sqrt(jnp.abs(jnp.diagonal(covariance)))
        valid = (jnp.all(jnp.isfinite(cholesky)) & jnp.isfinite(log_f)
                 & jnp.all(jnp.isfinite(scale)) & jnp.all(scale > 0))
        return mode, jnp.exp(log_f), jnp.clip(scale, 1e-6 * width, width), valid

    return jax.vmap(ascend)(starts)


def log_undercover(density, integral, modes, values, valid):
    r"""$\log(|f(m)| / (\hat I\,q(m)))$ at each of `modes` `(S, d)` for a density `q` with a
    `log_pdf` (`-inf` where not `valid`): in logs, since far from `q`'s parts its density
    underflows (in float32 first)."""
    integral = jnp.maximum(integral, jnp.finfo(values.dtype).tiny)
    log_ratio = jnp.log(values) - jnp.log(integral) - density.log_pdf(modes)
    return jnp.where(valid & ~jnp.isnan(log_ratio), log_ratio, -jnp.inf)


def grid_misses_a_mode(grid, integral, modes, values, valid):
    """Whether one of the `modes` is `UNDERCOVERED` by `grid` itself: the grid then misses
    mass its figure cannot show: its values never see the missing mode, so neither its
    variance nor its stream's error bar counts it."""
    return jnp.any(log_undercover(grid, integral, modes, values, valid) > math.log(UNDERCOVERED))


def with_modes(mixture: Mixture, integral, modes, values, scales, valid) -> Mixture:
    """`mixture` with a Gaussian at each of at most `MODE_COMPONENTS` undercovered modes
    (see the module's docstring), each in place of the fitted Gaussian of least weight (the
    wide one, last, stays; the shapes do not change); unchanged where none is undercovered."""
    d = modes.shape[-1]
    integral = jnp.maximum(integral, jnp.finfo(values.dtype).tiny)
    log_mass = jnp.log(values) + 0.5 * d * math.log(2 * math.pi) + jnp.sum(jnp.log(scales), axis=-1)
    for _ in range(MODE_COMPONENTS):
        log_ratio = log_undercover(mixture, integral, modes, values, valid)
        best = jnp.argmax(log_ratio)
        # Z / (I + Z), in logs.
        share = jnp.clip(jax.nn.sigmoid(log_mass[best] - jnp.log(integral)), MIN_SHARE, MAX_SHARE)
        gm = mixture.proposals[0]
        log_weights = jax.nn.log_softmax(gm.logits)
        slot = jnp.argmin(log_weights[:-1])
        # The others keep their proportions, in 1 - share of the weight.
        rest = log_weights - jnp.log1p(-jnp.exp(log_weights[slot])) + jnp.log1p(-share)
        placed = eqx.tree_at(
            lambda g: (g.logits, g.means, g.log_scales), gm,
            (rest.at[slot].set(jnp.log(share)), gm.means.at[slot].set(modes[best]),
             gm.log_scales.at[slot].set(jnp.log(scales[best]))),
        )
        undercovered = log_ratio[best] > math.log(UNDERCOVERED)
        gm = jax.tree.map(lambda new, old: jnp.where(undercovered, new, old), placed, gm)
        mixture = eqx.tree_at(lambda m: m.proposals[0], mixture, gm)
    return mixture
