r"""Control variates and antithetic variates for the uniform estimator."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from .. import _random
from .._box import clip_to_open_box, to_box
from .._checks import check_bounds, check_callable, check_count, check_key
from .._diagnostics import bounded_variance
from .._integrand import bind, evaluate, ratio
from .._stats import Estimate, diagnosed, estimate_iid, moments, tail_of


def _optimal_coefficient(y: jax.Array, z: jax.Array) -> jax.Array:
    r"""$\hat c = \widehat{\mathrm{Cov}}(y, z) / \widehat{V}(z)$ per output component (0 if $V(z) = 0$)."""
    dy = y - jnp.mean(y, axis=0)
    dz = z - jnp.mean(z, axis=0)
    cov = jnp.sum(dy * dz, axis=0)
    var = jnp.sum(dz * dz, axis=0)
    return jnp.where(var > 0, cov / jnp.where(var > 0, var, 1.0), 0.0)


def control_variate(
    key: jax.Array,
    f: Callable,
    g: Callable,
    g_integral: Any,
    lo: Any,
    hi: Any,
    n: int,
    *,
    batched: bool = False,
    args: Any = None,
) -> Estimate:
    r"""The uniform estimator with a control variate $g$ of known integral $G$.

    $$F = \frac{V}{n}\sum_{i=1}^n \bigl(f(X_i) - c\,(g(X_i) - G/V)\bigr),\qquad
    c^* = \frac{\mathrm{Cov}(f, g)}{V(g)},$$

    which has variance $(1 - \rho_{fg}^2)$ times the plain estimator's at the
    optimal $c^*$ (Owen, *Monte Carlo theory, methods and examples*, §8.9).

    **The coefficient is cross-fitted, so the estimate is exactly unbiased.**
    The samples are split into two halves $A$, $B$; $c$ is estimated on $B$ and
    applied to $A$, and vice versa. (Estimating $c$ on the very samples it
    corrects, the textbook regression estimator, has an $O(1/n)$ bias.) Given
    the other half, each half is an i.i.d. mean, so the reported variance is
    $(n_A s_A^2 + n_B s_B^2)/n^2$ from the halves' sample variances; it omits
    only an $O(1/n^2)$ covariance between the halves. The price of the split is
    an $O(1/n)$ relative increase in variance over the known-$c^*$ estimator.

    **Arguments:**

    - `key`: a PRNG key.
    - `f`: the integrand, written for one point (see `uniform`).
    - `g`: the control, written for one point; returns a scalar or an array of
      `f`'s output shape (each output component gets its own coefficient).
    - `g_integral`: $G = \int_{[lo, hi]} g$, broadcastable to `g`'s output.
    - `lo`, `hi`: the box.
    - `n`: number of samples (static int, at least 4: two per half).
    - `batched`: if True, `f` and `g` receive all points at once.
    - `args`: parameters (any pytree); if given, `f` and `g` are called as
      `f(x, args)` and `g(x, args)`.

    **Returns:** an `Estimate` (`n` evaluations of `f`, and of `g`).

    !!! Example

        ```python
        est = control_variate(key, jnp.exp, lambda x: 1 + x, 1.5, 0.0, 1.0, 1000)
        ```
    """
    key = check_key(key)
    f = bind(check_callable(f), args)
    g = bind(check_callable(g, "g"), args, "g")
    lo, hi = check_bounds(lo, hi)
    n = check_count(n, minimum=4)
    u = _random.uniform(key, (n,) + lo.shape, lo.dtype)
    x = to_box(u, lo, hi)
    fx = evaluate(f, x, batched)
    gx = evaluate(g, x, batched, name="g")
    if gx.shape[1:] not in ((), fx.shape[1:]):
        raise ValueError(
            f"`g` must return a scalar or an array of `f`'s output shape {fx.shape[1:]}, "
            f"got {gx.shape[1:]}."
        )
    G = jnp.asarray(g_integral, dtype=gx.dtype)
    try:
        ok = jnp.broadcast_shapes(G.shape, gx.shape[1:]) == gx.shape[1:]
    except ValueError:
        ok = False
    if not ok:
        raise ValueError(
            f"`g_integral` must broadcast to `g`'s output shape {gx.shape[1:]}, got {G.shape}."
        )
    volume = jnp.prod(hi - lo)
    p = jnp.broadcast_to(1.0 / volume, (n,))
    y, bad_f = ratio(fx, p)
    z, bad_g = ratio(gx, p)
    z = z - G  # E[V g(X)] = G
    if z.ndim < y.ndim:
        z = z.reshape(z.shape + (1,) * (y.ndim - z.ndim))
    z = jnp.broadcast_to(z, y.shape)
    half = n // 2
    ya, yb, za, zb = y[:half], y[half:], z[:half], z[half:]
    ca = _optimal_coefficient(ya, za)
    cb = _optimal_coefficient(yb, zb)
    ma = moments(ya - cb * za)
    mb = moments(yb - ca * zb)
    na, nb = half, n - half
    mean = (na * ma.mean + nb * mb.mean) / n
    variance = (na * ma.m2 / (na - 1) + nb * mb.m2 / (nb - 1)) / n**2
    contributions = jnp.concatenate([ya - cb * za, yb - ca * zb])
    return Estimate(**diagnosed(
        mean,
        variance,
        jnp.asarray(n, dtype=jnp.int32),
        jnp.sum(bad_f | bad_g, dtype=jnp.int32),
        tail_of(contributions),
    ))


def antithetic(
    key: jax.Array,
    f: Callable,
    lo: Any,
    hi: Any,
    n: int,
    *,
    batched: bool = False,
    args: Any = None,
) -> Estimate:
    r"""The uniform estimator with antithetic pairs $X$ and $lo + hi - X$.

    $$F = \frac{V}{n/2}\sum_{i=1}^{n/2} \frac{f(X_i) + f(lo + hi - X_i)}{2},$$

    unbiased; the pair means are i.i.d., so the variance is their sample
    variance over $n/2$ (under a power-law tail, at least the i.i.d. variance
    of all $n$ values: `bounded_variance`). It beats plain sampling at equal $n$ exactly when
    $\mathrm{Cov}(f(X), f(lo+hi-X)) < 0$, e.g. for $f$ monotone in each
    coordinate (Owen, §8.2); for $f$ symmetric about the centre it doubles the
    variance.

    **Arguments:**

    - `key`: a PRNG key.
    - `f`: the integrand, written for one point.
    - `lo`, `hi`: the box.
    - `n`: number of integrand evaluations (an even static int; `n/2` pairs).
    - `batched`: if True, `f` receives all `n` points at once.
    - `args`: parameters of `f` (any pytree); if given, `f` is called as `f(x, args)`.

    **Returns:** an `Estimate` with `n` evaluations.
    """
    key = check_key(key)
    f = bind(check_callable(f), args)
    lo, hi = check_bounds(lo, hi)
    n = check_count(n, minimum=2)
    if n % 2:
        raise ValueError(f"`n` must be even (n/2 antithetic pairs), got {n}.")
    pairs = n // 2
    u = _random.uniform(key, (pairs,) + lo.shape, lo.dtype)
    x = to_box(u, lo, hi)
    # The reflection can round onto a face: kept in the open box like every sample.
    x = jnp.concatenate([x, clip_to_open_box(lo + hi - x, lo, hi)])
    fx = evaluate(f, x, batched)
    volume = jnp.prod(hi - lo)
    y, bad = ratio(fx, jnp.broadcast_to(1.0 / volume, (n,)))
    pair_means = 0.5 * (y[:pairs] + y[pairs:])
    est = estimate_iid(pair_means, bad[:pairs] | bad[pairs:])
    # Pairs are a structure like strata: under a power-law tail their spread is skewed and
    # too small, so the i.i.d. variance of all values bounds it.
    variance, conservative = bounded_variance(est.variance, est.mean, tail_of(y))
    return dataclasses.replace(
        est,
        variance=variance,
        conservative=conservative,
        n=jnp.asarray(n, dtype=jnp.int32),
        n_nonfinite=jnp.sum(bad, dtype=jnp.int32),
    )
