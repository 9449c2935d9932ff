r"""The mixture in `integrate(method="auto")`'s pilot: seeded from the trained grid
(`_seeded_mixture`) and judged on the grid's own points (`mixture_outlook`), then, unless
that outlook is hopeless, given Gaussians at the modes it missed (`_mode_search`) and
measured on points of its own (`mixture_pilot`).

Its compiled programs are split where the integrand enters. What never evaluates $f$
(EM's fit and the outlook, the Gaussians placed at modes, the draw from the mixture) is
one program per shape, compiled once for every integrand of that dimension and budget;
only the ascent to the modes and the values $f/p$ are compiled for each integrand. Under
`jit` it is all one program, as before.
"""
from __future__ import annotations

import math
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp

from ._mode_search import differentiable, find_modes, grid_misses_a_mode, with_modes
from ._pilot_nets import net_points, relative_variance
from ._seeded_mixture import (
    _magnitude,
    fit_points,
    importance_weights,
    mixture_values,
    seeded_mixture,
)


# The mixture is a candidate only below this relative variance per evaluation, where
# its effective sample size n / (1 + v) is above n / 10 (`diagnostics.HEAVY_TAIL_ESS_SHARE`).
MIXTURE_MAX_VARIANCE = 9.0


# A trained grid this close a fit (relative variance per evaluation) whose values keep a
# power-law tail follows a singularity (`follows_a_singularity`).
SINGULAR_FIT = 1.0


def follows_a_singularity(qmc, grid_qmc, v_grid) -> jax.Array:
    r"""Whether the trained grid follows a singularity, which Gaussians do not: its figure
    `v_grid` is below `SINGULAR_FIT` while the values $f/q$ of QMC's nets through it
    (`grid_qmc`, `QMCFigures`) keep a power-law tail, as QMC's own values (`qmc`) did, QMC
    having seen the integrand. No mixture is then seeded from the grid (`auto`'s pilot,
    outside `jit`), nor judged first by `mixture_outlook` (EM on the grid's points).

    Measured, 3 keys at 1e5 and 1e6 on every `auto` benchmark case where a grid trains: it
    holds for the grids of $x^{-1/3}$ in 6-D, $x^{-1/2}$ in 2-D and $(\sum x)^{-3/2}$ in 4-D
    (figures 0.003-0.4), whose mixtures the outlook ruled hopeless on every key anyway (the
    estimates are unchanged: the suite's 66 bit for bit); where mixtures were measured
    (vegas's 4-D and i-flow's 8-D Gaussians, two 4-D Gaussians, i-flow's 16-D camel, a 5-D
    posterior, the 10-D ball) the values through the grid had no power-law tail, or the
    grid's figure was above 60 or unmeasured. Without the test of QMC's values it held on a
    2-D Gaussian of width 0.03 at $2^{15}$ (QMC blind, the grid at 0.054 with heavy values
    through it), where the mixture wins on 70 keys of 120; with it, 200 keys of narrow peaks
    in 2-D and 4-D choose and estimate as without the rule. `auto` on $x^{-1/3}$ in 6-D at
    1e5: 17-19 ms instead of 19.5-20 (fastest of 25 calls)."""
    return grid_qmc.heavy & (v_grid < SINGULAR_FIT) & qmc.heavy & ~qmc.blind


@jax.jit
def mixture_outlook(grid, samples):
    r"""The mixture $p$ seeded from the trained `grid`'s last round of `samples` (drawn from
    $q$, weights $w_i$), and its relative variance per evaluation judged on those points:
    $\hat E_p[(f/p)^2] / \hat I^2 - 1$ with $\hat E_p[(f/p)^2] = \sum_i w_i f_i^2/(p_i q_i)$
    (as $\int f^2/p = E_q[f^2/(p\,q)]$) and $\hat I = \sum_i w_i f_i/q_i$; $|f|$, in quadrature
    over an array-valued integrand's components. No evaluation of $f$: a look, before
    paying for the search for modes and the mixture's own points. It is in-sample (EM
    fitted $p$ to these points), and it knows nothing of the Gaussians the search may add.
    Measured against the mixture pilot's figure (4 keys at 1e5 and 1e6): 0.6-1.6x it on
    singularities ($x^{-1/3}$ in 6-D, $x^{-1/2}$ in 2-D, $(\sum x)^{-3/2}$ in 4-D), below it
    or near on the peaks where the mixture wins, up to 16x above it on the 5-D posterior
    and 13x on the 16-D camel, whose grids are far costlier still."""
    mixture = seeded_mixture(grid, samples)
    points = fit_points(samples)  # the points EM fitted, their weights normalised
    f = _magnitude(points.fx)
    w = points.weights / jnp.sum(points.weights) * jnp.exp(-points.log_q)
    integral = jnp.sum(w * f)
    second = jnp.sum(w * f**2 * jnp.exp(-mixture.log_pdf(points.x)))
    tiny = jnp.finfo(integral.dtype).tiny
    return mixture, second / jnp.maximum(integral**2, tiny) - 1


@eqx.filter_jit
def _modes(qmc_key, lo, hi, early, *, f, batched):
    """The modes near the QMC pilot's best points (`find_modes`; `early`: the values of its
    early look), or `None` where JAX cannot differentiate `f`: asked while this is traced
    (~12 ms a call if asked eagerly)."""
    if not differentiable(f, batched, lo):
        return None
    x = net_points(qmc_key, lo, hi, 0, 1, early.shape[1].bit_length() - 1)
    x = jnp.reshape(x, (-1, x.shape[-1]))
    return find_modes(f, batched, lo, hi, x,
                      _magnitude(jnp.reshape(early, (x.shape[0],) + early.shape[2:])))


def truncated_integral(weights) -> jax.Array:
    r"""$\hat I$ from a round's importance `weights` $c_i$ (`importance_weights`), each capped
    at $\sqrt{n}\,\bar c$ (truncated importance sampling, Ionides 2008): the scale against
    which `_mode_search` judges a mode undercovered, $|f(m)| > 10\,\hat I\,q(m)$, and sizes its
    Gaussian's share.

    A grid that holds one of two separated peaks samples the other rarely, at a tiny $q$:
    one such point inflates the round's plain sum, and with it $\hat I$, which then hides the
    very mode it came from. On i-flow's 16-D camel at 1e5, key 18, one point of 2048 made
    the sum 5.5 against the truth 0.86; the mixture's density at the missed mode then fell
    short of $|f|/\hat I$ by 5x, under the 10x that gets it a Gaussian, and the estimate came
    out at 0.57 of the truth (z = -11.7). Capped, $\hat I$ is biased low (never high), which
    makes the test only more ready to add a Gaussian at a mode; without such a point the cap
    is not reached and $\hat I$ is the plain sum."""
    n = weights.shape[0]
    cap = math.sqrt(n) * jnp.mean(weights)
    return jnp.sum(jnp.minimum(weights, cap))


@partial(jax.jit, static_argnames="size")
def _seeded_draw(key, mixture, grid, samples, modes, *, size):
    """The `mixture` seeded from `grid`'s `samples` with Gaussians at the `modes` it misses
    (if any were searched), and `size` points drawn from it: `(mixture, x, p(x), whether
    the grid misses a mode)`."""
    grid_misses = jnp.asarray(False)
    if modes is not None:
        integral = truncated_integral(importance_weights(samples))
        mixture = with_modes(mixture, integral, *modes)
        at, values, _, valid = modes
        grid_misses = grid_misses_a_mode(grid, integral, at, values, valid)
    x, p = mixture.sample(key, size)
    return mixture, x, p, grid_misses


@jax.jit
def _figures(y, grid_misses):
    """The mixture's relative variance per evaluation from its values `y` (`inf` where it
    fits loosely, see `mixture_pilot`), and whether it saw only zeros."""
    mean = jnp.mean(y, axis=0)
    variance = relative_variance(mean, jnp.var(y, axis=0, ddof=1))
    # A mixture that fits this loosely (effective sample size below a tenth: relative
    # variance above ~9) is no candidate: the grid's figure is of its last training
    # round, and it goes on adapting, the mixture does not (on the 10-D ball the trained
    # grid measured 200-2000 and then ran at ~4, against the mixture's 14-390). Unless the
    # grid misses a mode the mixture was given: its figure then hides the missing mass.
    loose = (variance > MIXTURE_MAX_VARIANCE) & ~grid_misses
    # Blind only if it saw nothing: a few large values are the defensive share's
    # (bounded, see `_auto`'s docstring), not a missed peak's.
    return jnp.where(loose, jnp.inf, variance), jnp.all(mean == 0)


def mixture_pilot(key, mixture, grid, samples, qmc_key, early, *, f, size, batched):
    """Give the `mixture` seeded from `grid`'s `samples` (`mixture_outlook`) Gaussians at the
    modes it missed (`_mode_search`, from the best points of the QMC pilot's early look,
    `early` its values), and measure it on `size` points: `(relative variance per
    evaluation, blind, the mixture, its points and values, whether the modes were
    searched, whether the grid misses one)`."""
    modes = _modes(qmc_key, grid.lo, grid.hi, early, f=f, batched=batched)
    mixture, x, p, grid_misses = _seeded_draw(key, mixture, grid, samples, modes, size=size)
    y = mixture_values(x, p, f=f, batched=batched)
    variance, blind = _figures(y, grid_misses)
    return variance, blind, mixture, (x, y), modes is not None, grid_misses
