"""Evaluating an integrand on a batch of points, and the ratio $f/p$ every estimator uses.

Every estimator, adaptation rule and fit goes through `evaluate` (one point at
a time by `vmap`, or the whole batch with `batched=True`) and `ratio` (the
per-sample value $f(x)/p(x)$, non-finite values counted and zeroed), so the
conventions for shapes, dtypes and non-finite values live here alone.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp


def evaluate(f: Callable, x: jax.Array, batched: bool, name: str = "f") -> jax.Array:
    """Evaluate an integrand on a batch `x` of shape `(n, ...)`.

    `f` is written for one point unless `batched`; the result has shape
    `(n, *out_shape)` and a floating dtype.
    """
    n = x.shape[0]
    y = f(x) if batched else jax.vmap(f)(x)
    y = jnp.asarray(y)
    if y.ndim == 0 or y.shape[0] != n:
        raise ValueError(
            f"`{name}` with batched=True must return an array with leading axis {n}, "
            f"got shape {y.shape}."
            if batched
            else f"`{name}` returned an unexpected shape {y.shape}."
        )
    if not jnp.issubdtype(y.dtype, jnp.inexact):
        y = y.astype(jnp.result_type(float))
    elif jnp.issubdtype(y.dtype, jnp.complexfloating):
        raise TypeError(f"`{name}` must return real values, got dtype {y.dtype}.")
    return y


def ratio(fx: jax.Array, px: jax.Array) -> tuple[jax.Array, jax.Array]:
    """`f(x)/p(x)` per sample with the conventions of every estimator.

    Returns `(y, bad)`: `y` has `fx`'s shape; where `p = 0` and `f = 0` the
    ratio is 0 (the sample carries no mass); where `f/p` is not finite (a
    non-finite `f`, or `p = 0` with `f != 0`), `y` is 0 and `bad` is True, so the
    estimate stays finite and the problem is counted in `n_nonfinite`.
    """
    px = jnp.reshape(px, px.shape + (1,) * (fx.ndim - px.ndim))
    safe_p = jnp.where(px > 0, px, 1.0)
    y = jnp.where(px > 0, fx / safe_p, jnp.where(fx == 0, 0.0, jnp.inf))
    finite = jnp.isfinite(y)
    y = jnp.where(finite, y, 0.0)
    bad = ~jnp.all(finite.reshape(finite.shape[0], -1), axis=1)
    return y, bad
