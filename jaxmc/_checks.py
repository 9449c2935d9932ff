"""Trace-time argument checks shared by every public entry point.

Each check raises `ValueError`/`TypeError` naming the offending argument, and
runs in Python before anything is traced, so bad input fails early with a clear
message instead of surfacing later as a NaN. Checks that need values (e.g.
`lo < hi`) run only when the values are concrete; under `jit` with traced
bounds they are skipped rather than turned into runtime errors.
"""

from __future__ import annotations

import operator
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


def is_concrete(x: Any) -> bool:
    """True when `x` holds values known at trace time (not a tracer)."""
    return not isinstance(x, jax.core.Tracer)


def check_key(key: Any, name: str = "key") -> jax.Array:
    """Accept a typed key (`jax.random.key`) or a legacy `PRNGKey`; reject batches."""
    if not isinstance(key, jax.Array):
        raise TypeError(
            f"`{name}` must be a JAX PRNG key from jax.random.key(...) or "
            f"jax.random.PRNGKey(...), got {type(key).__name__}."
        )
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        if key.shape != ():
            raise ValueError(
                f"`{name}` must be a single key, got a batch of shape {key.shape}. "
                "Use jax.vmap for batching."
            )
        return key
    if key.dtype != jnp.uint32 or key.ndim != 1:
        raise TypeError(
            f"`{name}` must be a JAX PRNG key (typed, or a legacy uint32 array of shape (2,)), "
            f"got dtype {key.dtype} and shape {key.shape}. "
            + ("Use jax.vmap for batching." if key.ndim > 1 else "")
        )
    return key


def check_count(n: Any, name: str = "n", minimum: int = 1) -> int:
    """A static, positive Python int (sizes are static in jaxmc)."""
    if isinstance(n, bool):
        raise TypeError(f"`{name}` must be an int, got a bool.")
    try:
        value = operator.index(n)
    except TypeError:
        raise TypeError(
            f"`{name}` must be a Python int (sizes are static), got {type(n).__name__} {n!r}."
        ) from None
    if value < minimum:
        raise ValueError(f"`{name}` must be >= {minimum}, got {value}.")
    return value


def check_choice(value: Any, name: str, choices: tuple[str, ...]) -> str:
    if not isinstance(value, str) or value not in choices:
        raise ValueError(f"`{name}` must be one of {choices}, got {value!r}.")
    return value


def check_bounds(lo: Any, hi: Any) -> tuple[jax.Array, jax.Array]:
    """Bounds of a box: both scalars or both of shape `(d,)`, with `lo < hi`.

    Returns floating arrays of the default float dtype (or of the bounds' own
    floating dtype).
    """
    lo_arr = jnp.asarray(lo)
    hi_arr = jnp.asarray(hi)
    dtype = jnp.result_type(lo_arr.dtype, hi_arr.dtype, float)
    lo_arr, hi_arr = lo_arr.astype(dtype), hi_arr.astype(dtype)
    if lo_arr.ndim > 1 or hi_arr.ndim > 1:
        raise ValueError(
            f"`lo` and `hi` must be scalars or of shape (d,), got shapes {lo_arr.shape} "
            f"and {hi_arr.shape}."
        )
    if lo_arr.shape != hi_arr.shape:
        raise ValueError(
            f"`lo` and `hi` must have the same shape, got {lo_arr.shape} and {hi_arr.shape}."
        )
    if lo_arr.shape == (0,):
        raise ValueError("`lo` and `hi` must have at least one dimension, got shape (0,).")
    if is_concrete(lo_arr) and is_concrete(hi_arr):
        lo_np, hi_np = np.asarray(lo_arr), np.asarray(hi_arr)
        if not (np.all(np.isfinite(lo_np)) and np.all(np.isfinite(hi_np))):
            raise ValueError(f"`lo` and `hi` must be finite, got lo={lo_np}, hi={hi_np}.")
        if not np.all(lo_np < hi_np):
            raise ValueError(f"`lo` must be < `hi` in every dimension, got lo={lo_np}, hi={hi_np}.")
    return lo_arr, hi_arr


def check_callable(f: Any, name: str = "f") -> Callable:
    if not callable(f):
        raise TypeError(f"`{name}` must be callable, got {type(f).__name__}.")
    return f

