r"""What a candidate's pilot measured: its relative variance per evaluation and how sure it is.

A method whose estimate from $m$ evaluations has variance $\sigma^2_m$ has *variance per
evaluation* $v = m\,\sigma^2_m$; relative, $v/I^2$ (summed over an array-valued integrand's
components), it is scale-free. Spending $n$ more evaluations on the method gives variance
about $v/n$. A pilot estimates $v$ from few points, so every `Figure` carries the standard
deviation of $\log \hat v$:

- from $n$ i.i.d. values of kurtosis $\kappa$, $\operatorname{Var}\log s^2 \approx
  (\kappa - 1)/n$ (the delta method on the sample variance);
- from $R$ replicas (randomised QMC's nets), the jackknife over the replicas (Efron and
  Stein 1981) of the whole figure, its projection to larger nets included.

A figure whose values have a power-law tail (Pareto $\hat k$ above 1/4, as
`jaxmc.stats` reads it) is the i.i.d. variance the stream will report there
(`bounded_variance`), and its $\log$ has no finite standard deviation to speak of
(the sample fourth moment diverges for $k \ge 1/4$).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .._diagnostics import (
    HEAVY_TAIL_ESS_SHARE,
    STRUCTURED_MAX_PARETO_K,
    pareto_k,
    tail_of,
)


# Fewer effective points per replica than this measured nothing: the replicas' means rest
# on a handful of hits each, and their spread says little of the variance.
MIN_ESS_PER_REPLICA = 8.0
# A density held fixed through its stream whose pilot values have fewer effective points
# than this share of their number is no candidate: by `jaxmc.stats.unreliable` a few
# points carry its mean, and its figure is itself unreliable.
MIN_ESS_SHARE = HEAVY_TAIL_ESS_SHARE


class Figure(eqx.Module):
    """A candidate's relative variance per evaluation (`value`, `inf` where unmeasured) and
    the standard deviation of its logarithm (`log_sd`)."""

    value: jax.Array
    log_sd: jax.Array

    def low(self, z) -> jax.Array:
        """The figure `z` standard deviations below (in logs): an optimistic bound."""
        return self.value * jnp.exp(-z * self.log_sd)

    def high(self, z) -> jax.Array:
        """The figure `z` standard deviations above: a pessimistic bound."""
        return self.value * jnp.exp(z * self.log_sd)


def unmeasured(dtype) -> Figure:
    """A figure for a candidate whose stage did not run: nothing known."""
    return Figure(jnp.full((), jnp.inf, dtype), jnp.full((), jnp.inf, dtype))


def relative_variance(mean, variance) -> jax.Array:
    """Variance scaled by the squared mean, summed over the components (the last axes of
    `mean` and `variance`, after any leading batch axes of `lead` dimensions); scale-free."""
    tiny = jnp.finfo(mean.dtype).tiny
    ratio = jnp.where(mean != 0, variance / jnp.maximum(mean**2, tiny), variance)
    return jnp.sum(ratio)


def magnitude(values) -> jax.Array:
    """Each row's $|y|$, in quadrature over an array-valued integrand's components."""
    y = jnp.reshape(values, (values.shape[0], -1))
    return jnp.sqrt(jnp.sum(jnp.where(jnp.isfinite(y), y, 0) ** 2, axis=-1))


def effective_points(values) -> jax.Array:
    r"""$(\sum_i |y_i|)^2 / \sum_i y_i^2$ of the rows of `values` (the smallest over the
    components): about 1 where one value carries the mean."""
    flat = jnp.reshape(values, (values.shape[0], -1))
    tiny = jnp.finfo(flat.dtype).tiny
    return jnp.min(jnp.sum(jnp.abs(flat), axis=0) ** 2
                   / jnp.maximum(jnp.sum(flat**2, axis=0), tiny))


def suspected_tail(values, tail=None) -> jax.Array:
    r"""Whether `values` `(n, ...)` may have a power-law tail: their Pareto $\hat k$ above
    `STRUCTURED_MAX_PARETO_K` (1/4, where `jaxmc.stats` bounds a structured variance by the
    i.i.d. one); their kurtosis, and with it the figure's uncertainty, is then not known.
    `tail`: the values' `tail_of`, where the caller has it."""
    tail = tail_of(values) if tail is None else tail
    return jnp.any(pareto_k(tail) > STRUCTURED_MAX_PARETO_K)


def iid_figure(values, tail=None) -> tuple[Figure, jax.Array]:
    r"""The figure of i.i.d. `values` `(n, ...)` ($f/p$ at points drawn from $p$): the sample's
    relative variance per evaluation, $\log$'s standard deviation $\sqrt{(\kappa - 1)/n}$ from
    the kurtosis $\kappa$ of their magnitudes, and whether their tail may be a power law
    (`suspected_tail`, given the values' `tail` where the caller has it). A sample whose mean
    is 0 measured nothing (`inf`)."""
    n = values.shape[0]
    mean = jnp.mean(values, axis=0)
    v = relative_variance(mean, jnp.var(values, axis=0, ddof=1))
    a = magnitude(values)
    centred = a - jnp.mean(a)
    m2 = jnp.mean(centred**2)
    kurtosis = jnp.mean(centred**4) / jnp.maximum(m2**2, jnp.finfo(a.dtype).tiny)
    log_sd = jnp.sqrt(jnp.maximum(kurtosis - 1, 2.0) / n)
    suspected = suspected_tail(values, tail)
    seen = jnp.any(mean != 0)
    return (Figure(jnp.where(seen, v, jnp.inf), jnp.where(seen & ~suspected, log_sd, jnp.inf)),
            suspected)


def frozen_figure(values, misses_mass=False) -> Figure:
    """`iid_figure` of the values $f/q$ of a density held fixed through its stream, no
    candidate (`inf`) below `MIN_ESS_SHARE` effective points, unless `misses_mass` says the
    alternative (a grid) misses a mode this density holds."""
    figure, _ = iid_figure(values)
    loose = (effective_points(values) < MIN_ESS_SHARE * values.shape[0]) & ~misses_mass
    return Figure(jnp.where(loose, jnp.inf, figure.value), figure.log_sd)


def blind(values, replicas: int) -> jax.Array:
    """Whether values `(n, ...)` saw nothing: all zero, or fewer than `MIN_ESS_PER_REPLICA`
    effective points a replica."""
    flat = jnp.reshape(values, (values.shape[0], -1))
    return jnp.all(flat == 0) | (effective_points(values) < MIN_ESS_PER_REPLICA * replicas)
