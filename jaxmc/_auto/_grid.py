r"""The grid's stage of `Auto`'s pilot, measured: the trained VEGAS+ grid's last rounds
(`adaptive_figure`) and QMC's nets carried through its map (`grid_qmc_figure`)."""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from .._diagnostics import bounded_variance, tail_of
from .._integrand import ratio
from .._methods._edged_grid import edged
from .._stats import scatter_bound
from ._figures import MIN_ESS_SHARE, Figure, blind, effective_points, iid_figure, relative_variance
from ._nets import REPLICAS, credited_figures, mapped_net_values


@partial(jax.jit, static_argnames="round_size")
def adaptive_figure(parts, samples, z, *, round_size) -> Figure:
    r"""The trained grid's figure from its training rounds' estimates `parts` and the last
    round's `samples`: `(Figure, whether its values f/q have a power-law tail)`.

    The figure is the last round's variance (its i.i.d. bound under a power-law tail, as the
    stream reports it there), times its points. That variance comes from pairs of points in
    hypercubes, which a peak the grid has not yet resolved inflates; the scatter of the last
    rounds' means is a second estimate: the figure is kept at most at its bound `z`
    standard deviations above (`scatter_bound`). Its logarithm's standard deviation is the
    last round's values' (`iid_figure`)."""
    values, _ = ratio(samples.fx, jnp.exp(samples.log_q))
    tail = tail_of(values)
    variance, _ = bounded_variance(parts.variance[-1], parts.mean[-1], tail)
    v_last = relative_variance(parts.mean[-1], variance) * round_size
    cap = scatter_bound(parts.mean, round_size, z)
    seen = jnp.any(parts.mean[-1] != 0)
    own, _ = iid_figure(values)
    return Figure(jnp.where(seen, jnp.minimum(v_last, cap), jnp.inf), own.log_sd)


def grid_qmc_values(key, grid, f, batched, log2_size):
    """QMC's pilot nets through the trained `grid`'s map, bent at the faces where it follows
    a singularity (`EdgedGrid`), as `GridQMC` streams."""
    return mapped_net_values(key, edged(grid), f, batched, log2_size)


@jax.jit
def grid_qmc_figure(y, fx, growth) -> Figure:
    """QMC's figure through the grid, from its nets' values `y` `(R, m, ...)` (as QMC's own,
    `qmc_figure`, projected `growth`-fold), `fx` the integrand's values there: no candidate
    where the values saw nothing or have fewer effective points than `MIN_ESS_SHARE` of
    their number (a loose fit). Credited as its stream would report it, given f's values as
    that stream through a grid gives them (`credited_figures`), as QMC's figure is."""
    figure, _, _ = credited_figures(y, growth, fx)
    flat = jnp.reshape(y, (-1,) + y.shape[2:])
    loose = effective_points(flat) < MIN_ESS_SHARE * flat.shape[0]
    unfit = loose | blind(flat, REPLICAS)
    return Figure(jnp.where(unfit, jnp.inf, figure.value), figure.log_sd)
