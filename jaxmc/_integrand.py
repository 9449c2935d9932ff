"""Evaluating an integrand on a batch of points, and the ratio $f/p$ every estimator uses.

Every estimator, adaptation rule and fit goes through `evaluate` (one point at
a time by `vmap`, or the whole batch with `batched=True`) and `ratio` (the
per-sample value $f(x)/p(x)$, non-finite values counted and zeroed), so the
conventions for shapes, dtypes and non-finite values live here alone. An
integrand given `args` is bound to them by `bind` (`WithArgs`), so that the
parameters reach every compiled function as traced arguments.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._checks import as_real_array, check_callable, check_flag


class WithArgs(eqx.Module):
    """`f` bound to its parameters: `WithArgs(f, args)(x)` is `f(x, args)`.

    A pytree whose leaves are `args`' arrays (and those of `f` itself, if it is
    a module): `equinox.filter_jit` traces them and keys its cache on the rest,
    so the same `f` with new `args` of the same shapes and dtypes reuses the
    compiled code, where a new closure over the values would be traced and
    compiled anew.
    """

    f: Callable
    args: Any

    def __call__(self, x: jax.Array) -> Any:
        return self.f(x, self.args)


def _traced(leaf: Any) -> Any:
    """Python floats (and complex numbers) and NumPy values as JAX arrays, so they are traced.

    Python ints and bools stay as they are: static, like `equinox.filter_jit`'s,
    so they may set shapes or branch in Python (each new value compiles anew).
    """
    if isinstance(leaf, (bool, int)):
        return leaf
    if isinstance(leaf, (float, complex, np.ndarray, np.generic)):
        return jnp.asarray(leaf)
    return leaf


def bind(f: Callable, args: Any, name: str = "f") -> Callable:
    """`f` itself when `args` is None, else `WithArgs(f, args)` with `args`' numbers as arrays.

    `f` must then accept two positional arguments, `(x, args)`.
    """
    if args is None:
        return f
    check_callable(f, name, arguments=2)
    return WithArgs(f, jax.tree.map(_traced, args))


def evaluate(f: Callable, x: jax.Array, batched: bool, name: str = "f") -> jax.Array:
    """Evaluate an integrand on a batch `x` of shape `(n, ...)`.

    `f` is written for one point unless `batched`; the result has shape
    `(n, *out_shape)` and a floating dtype. Errors name `f` and say how it was
    called, never the internal batch size.
    """
    check_callable(f, name, arguments=1)
    batched = check_flag(batched, "batched")
    n = x.shape[0]
    point = str(("batch",) + x.shape[1:]).replace("'", "") if batched else str(x.shape[1:])

    def call(points):
        try:
            return f(points)
        except Exception as error:  # the user's own error: say how jaxmc called `f`
            if hasattr(error, "add_note"):  # Python >= 3.11
                where = "a batch of points" if batched else "one point"
                how = f" as {name}(x, args)" if isinstance(f, WithArgs) else ""
                scalar = " (scalar bounds `lo`, `hi` give scalar points)" if x.ndim == 1 else ""
                # (Indexing a point as a batch, x[:, 0] or axis=1, fails so.)
                hint = ("; an integrand written for a batch of points of shape (m, d) needs "
                        "batched=True" if not batched and isinstance(error, (IndexError, ValueError))
                        else "")
                error.add_note(f"(raised by the integrand `{name}`, which jaxmc calls{how} on {where} "
                               f"x of shape {point} and dtype {x.dtype}{scalar}{hint})")
            raise

    y = _values(call(x), name) if batched else jax.vmap(lambda xi: _values(call(xi), name))(x)
    if batched and (y.ndim == 0 or y.shape[0] != n):
        raise ValueError(
            f"`{name}` with batched=True is called on a batch of points x of shape {point} and "
            f"must return one value per point: an array of shape (batch,) or (batch, ...) whose "
            f"leading axis is x.shape[0]; it returned shape {y.shape}."
        )
    return y


def _values(y: Any, name: str) -> jax.Array:
    """An integrand's output as a floating array (booleans and integers are converted)."""
    y = as_real_array(y, f"`{name}` must return a real number or an array of real numbers")
    return y if jnp.issubdtype(y.dtype, jnp.floating) else y.astype(jnp.result_type(float))


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
