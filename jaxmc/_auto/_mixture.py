r"""The mixture's part of `Auto`'s pilot: seeded from the trained grid and judged on the
grid's own points (`mixture_outlook`); the modes near QMC's best points, and whether the
grid misses one (`search_modes`); the mixture, given Gaussians at those it misses, measured
on points of its own (`mixture_pilot`).

What never evaluates $f$ (EM's fit and the outlook, the Gaussians placed at modes, the draw)
is compiled once per shape, for every integrand of that dimension and budget; only the
ascent to the modes and the values $f/p$ are compiled for each integrand.
"""

from __future__ import annotations

import math
from functools import partial

import jax
import jax.numpy as jnp

from .._box import to_box
from .._compiled import per_integrand
from .._methods._seeded_mixture import (
    fit_points,
    importance_weights,
    mixture_values,
    seeded_mixture,
)
from ._figures import frozen_figure, magnitude
from ._modes import differentiable, find_modes, grid_misses_a_mode, with_modes
from ._nets import _net_units


@jax.jit
def mixture_outlook(grid, samples):
    r"""The mixture $p$ seeded from the trained `grid`'s last round of `samples` (drawn from
    $q$, weights $w_i$), and its relative variance per evaluation read on those points:
    $\hat E_p[(f/p)^2] / \hat I^2 - 1$ with $\hat E_p[(f/p)^2] = \sum_i w_i f_i^2/(p_i q_i)$
    (as $\int f^2/p = E_q[f^2/(p\,q)]$) and $\hat I = \sum_i w_i f_i/q_i$. No evaluation of
    $f$; in-sample (EM fitted $p$ to these points), so it flatters the mixture."""
    mixture = seeded_mixture(grid, samples)
    points = fit_points(samples)
    f = magnitude(points.fx)
    w = points.weights / jnp.sum(points.weights) * jnp.exp(-points.log_q)
    integral = jnp.sum(w * f)
    second = jnp.sum(w * f**2 * jnp.exp(-mixture.log_pdf(points.x)))
    tiny = jnp.finfo(integral.dtype).tiny
    return mixture, jnp.maximum(second / jnp.maximum(integral**2, tiny) - 1, 0)


@per_integrand
def _modes(qmc_key, lo, hi, early, *, f, batched):
    """The modes near the QMC pilot's best points (`find_modes`; `early`: its early look's
    values, on the pilot's first nets), or `None` where JAX cannot differentiate `f`
    (asked while this is traced: eagerly, ~12 ms a call)."""
    if not differentiable(f, batched, lo):
        return None
    u = _net_units(qmc_key, lo.shape[0], lo.dtype, 0, 1, early.shape[1].bit_length() - 1)
    x = to_box(jnp.reshape(u, (-1, lo.shape[0])), lo, hi)
    return find_modes(f, batched, lo, hi, x,
                      magnitude(jnp.reshape(early, (x.shape[0],) + early.shape[2:])))


def truncated_integral(weights) -> jax.Array:
    r"""$\hat I$ from a round's importance `weights` $c_i$ (`importance_weights`), each capped
    at $\sqrt{n}\,\bar c$ (truncated importance sampling, Ionides 2008): the scale against
    which a mode is judged undercovered. A grid that holds one of two separated peaks samples
    the other rarely, at a tiny $q$: one such point inflates the plain sum, and with it
    $\hat I$, which would then hide the very mode it came from. Capped, $\hat I$ is biased
    low, which only makes the test readier to add a Gaussian."""
    n = weights.shape[0]
    cap = math.sqrt(n) * jnp.mean(weights)
    return jnp.sum(jnp.minimum(weights, cap))


def search_modes(qmc_key, early, grid, samples, *, f, batched):
    """The modes near the QMC pilot's best points (`early`: its early look's values), where
    JAX can differentiate `f` (else `None`), and whether the trained `grid` misses one of
    them (`grid_misses_a_mode`, against the grid's last round of `samples`)."""
    modes = _modes(qmc_key, grid.lo, grid.hi, early, f=f, batched=batched)
    return modes, (jnp.asarray(False) if modes is None else _misses(grid, samples, modes))


@jax.jit
def _misses(grid, samples, modes):
    at, values, _, valid = modes
    integral = truncated_integral(importance_weights(samples))
    return grid_misses_a_mode(grid, integral, at, values, valid)


@partial(jax.jit, static_argnames="size")
def _seeded_draw(key, mixture, samples, modes, *, size):
    """`mixture` with Gaussians at the `modes` it misses (if searched), and `size` points
    drawn from it: `(mixture, x, p(x))`."""
    if modes is not None:
        mixture = with_modes(mixture, truncated_integral(importance_weights(samples)), *modes)
    return (mixture,) + mixture.sample(key, size)


def mixture_pilot(key, mixture, samples, modes, grid_misses, *, f, size, batched):
    """Give the seeded `mixture` Gaussians at the `modes` it missed (`search_modes`) and
    measure it on `size` points: `(its Figure, the mixture, its points and values)`."""
    mixture, x, p = _seeded_draw(key, mixture, samples, modes, size=size)
    y = mixture_values(x, p, f=f, batched=batched)
    return _figure(y, grid_misses), mixture, (x, y)


@jax.jit
def _figure(y, grid_misses):
    """The mixture's figure (`frozen_figure`): a loose fit is none, unless the grid misses a
    mode the mixture was given (the grid's own figure then hides the missing mass)."""
    return frozen_figure(y, grid_misses)
