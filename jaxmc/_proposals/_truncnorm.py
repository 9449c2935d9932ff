r"""The truncated normal distribution in both tails: $\log(\Phi(b) - \Phi(a))$ and its inverse CDF."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.scipy.special import log_ndtr, ndtr, ndtri

from .._box import clip_to_open_box


def log_ndtr_diff(a: jax.Array, b: jax.Array) -> jax.Array:
    r"""$\log(\Phi(b) - \Phi(a))$ for $a < b$, accurate in both tails.

    Reflects to the lower tail ($\Phi(b) - \Phi(a) = \Phi(-a) - \Phi(-b)$) where
    that keeps the difference of two small numbers, and subtracts in log space.
    """
    flip = a > 0
    lo = jnp.where(flip, -b, a)
    hi = jnp.where(flip, -a, b)
    log_hi = log_ndtr(hi)
    log_lo = log_ndtr(lo)
    # log(exp(log_hi) - exp(log_lo)) = log_hi + log1p(-exp(log_lo - log_hi)).
    return log_hi + jnp.log1p(-jnp.exp(jnp.minimum(log_lo - log_hi, -1e-300)))


def truncnorm_icdf(u: jax.Array, mu: jax.Array, sigma: jax.Array, lo, hi, component=None) -> jax.Array:
    r"""Inverse CDF of $\mathcal N(\mu, \sigma^2)$ truncated to $[lo, hi]$ at `u`.

    $x = \mu + \sigma\,\Phi^{-1}(\Phi(a) + u(\Phi(b) - \Phi(a)))$ with
    $a = (lo-\mu)/\sigma$, $b = (hi-\mu)/\sigma$, computed on the side of the
    mean where the CDF values are not close to 1 (so both tails keep their
    precision). Differentiable in $\mu$, $\sigma$: the reparameterised sample.
    The result lies strictly inside $(lo, hi)$, never on a face.

    With `component` (integer indices `(n,)`), `mu` and `sigma` are per
    component `(K, ...)` and point $i$ of `u` `(n, ...)` is drawn from component
    `component[i]`: $\Phi(a)$ and $\Phi(b)$ are then computed once per component
    rather than per point (they are the dearest part).
    """
    a = (lo - mu) / sigma
    b = (hi - mu) / sigma
    flip = (a + b) > 0  # box mostly above the mean: work with the reflected variable
    a2 = jnp.where(flip, -b, a)
    b2 = jnp.where(flip, -a, b)
    pa = ndtr(a2)
    pb = ndtr(b2)
    # Far in the lower tail Phi underflows; there the truncated normal is an
    # exponential with rate |b| below b (Mills ratio), inverted in closed form.
    lam = jnp.maximum(-b2, 1.0)
    e_t = jnp.exp(-lam * (b2 - a2))
    if component is not None:
        # Stacked and materialised once: gathered one by one, XLA fused `ndtr` (and the
        # tail's exponential) into the gathers outside loops, computing them per point.
        table = jnp.stack(jnp.broadcast_arrays(mu, sigma, a2, b2, pa, pb, lam, e_t))
        table = jax.lax.optimization_barrier(table)
        flip = flip[component]
        mu, sigma, a2, b2, pa, pb, lam, e_t = (table[i][component] for i in range(8))
    u2 = jnp.where(flip, 1 - u, u)
    eps = jnp.finfo(jnp.result_type(u)).tiny
    z = ndtri(jnp.clip(pa + u2 * (pb - pa), eps, 1 - jnp.finfo(jnp.result_type(u)).epsneg))
    t = -jnp.log(u2 * (1 - e_t) + e_t) / lam
    z = jnp.where(b2 < -30.0, b2 - t, z)
    z = jnp.clip(z, a2, b2)
    z = jnp.where(flip, -z, z)
    return clip_to_open_box(mu + sigma * z, lo, hi)

