"""Trace-time argument checks shared by every public entry point.

Each check raises `ValueError`/`TypeError` naming the offending argument, and
runs in Python before anything is traced, so bad input fails early with a clear
message instead of surfacing later as a NaN. Checks that need values (e.g.
`lo < hi`) run only when the values are concrete; under `jit` with traced
bounds they are skipped rather than turned into runtime errors.
"""

from __future__ import annotations

import inspect
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


MAX_COUNT = 2**31 - 1  # evaluation counts are int32 on the device: the cap of every budget


def check_count(n: Any, name: str = "n", minimum: int = 1, maximum: int | None = None) -> int:
    """A static Python int in `[minimum, maximum]` (sizes are static in jaxmc)."""
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
    if maximum is not None and value > maximum:
        limit = "2**31 - 1 (counts are int32)" if maximum == MAX_COUNT else str(maximum)
        raise ValueError(f"`{name}` must be at most {limit}, got {value}.")
    return value


def check_flag(value: Any, name: str) -> bool:
    """A Python bool (a static switch, not an array)."""
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"`{name}` must be a bool (True or False), got {type(value).__name__} {value!r}.")
    return bool(value)


def check_choice(value: Any, name: str, choices: tuple[str, ...]) -> str:
    if not isinstance(value, str) or value not in choices:
        raise ValueError(f"`{name}` must be one of {choices}, got {value!r}.")
    return value


def check_bounds(
    lo: Any, hi: Any, finite_volume: bool = False, infinite: bool = False
) -> tuple[jax.Array, jax.Array]:
    """Bounds of a box: both scalars or both of shape `(d,)`, with `lo < hi`.

    Returns floating arrays of the default float dtype (or of the bounds' own
    floating dtype). With `finite_volume` (for estimators that divide by the
    volume, rather than summing its logarithm), the volume and the uniform
    density must be finite and non-zero in that dtype. With `infinite` (for
    `integrate` and `expectation`, which map infinite axes onto finite
    intervals), `lo` may hold -inf and `hi` +inf; the volume is then
    checked on the finite axes only.
    """
    host = _host_reals(lo), _host_reals(hi)
    if host[0] is not None and host[1] is not None:
        # Plain numbers: cast in NumPy, one transfer each (eager jnp casts are a sizeable
        # share of a small `integrate` call).
        canonical = (jax.dtypes.canonicalize_dtype(a.dtype) for a in host)
        dtype = jnp.result_type(*canonical, float)
        with np.errstate(all="ignore"):  # a float32 overflow shows up as inf, checked below
            lo_np, hi_np = (a.astype(dtype) for a in host)
        lo_arr, hi_arr = jnp.asarray(lo_np), jnp.asarray(hi_np)
    else:
        lo_arr = as_real_array(lo, "`lo` must be a real number or a sequence of them")
        hi_arr = as_real_array(hi, "`hi` must be a real number or a sequence of them")
        dtype = jnp.result_type(lo_arr.dtype, hi_arr.dtype, float)
        lo_arr, hi_arr = lo_arr.astype(dtype), hi_arr.astype(dtype)
        # The values as given (under jit even a Python list is staged by jnp.asarray).
        lo_np, hi_np = _host_values(lo, dtype), _host_values(hi, dtype)
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
    if lo_np is not None and hi_np is not None:
        if np.any(np.isnan(lo_np)) or np.any(np.isnan(hi_np)):
            raise ValueError(f"`lo` and `hi` must not be NaN, got lo={lo_np}, hi={hi_np}.")
        if not infinite and not (np.all(np.isfinite(lo_np)) and np.all(np.isfinite(hi_np))):
            raise ValueError(
                f"`lo` and `hi` must be finite here, got lo={lo_np}, hi={hi_np}; "
                "jaxmc.integrate and jaxmc.expectation accept infinite limits."
            )
        if not np.all(lo_np < hi_np):
            raise ValueError(f"`lo` must be < `hi` in every dimension, got lo={lo_np}, hi={hi_np}.")
        if finite_volume:
            finite = np.isfinite(lo_np) & np.isfinite(hi_np)
            _check_volume(lo_np[finite], hi_np[finite], dtype)
    return lo_arr, hi_arr


def as_real_array(value: Any, requirement: str) -> jax.Array:
    """`value` as an array of real numbers (booleans, integers or floats), else a `TypeError`
    reading `requirement` (e.g. "`lo` must be a real number or a sequence of them")."""
    if not isinstance(value, jax.Array):
        try:  # numpy first: jnp would read a string as a dtype name
            kind = np.asarray(value).dtype.kind
        except Exception:  # ragged, or holding tracers: jnp.asarray decides
            kind = "?"
        if kind not in "biuf?":
            raise TypeError(f"{requirement}, got {type(value).__name__} {_abbreviated(value)}.")
    try:
        arr = jnp.asarray(value)
    except (TypeError, ValueError):
        raise TypeError(f"{requirement}, got {type(value).__name__} {_abbreviated(value)}.") from None
    if not any(jnp.issubdtype(arr.dtype, t) for t in (jnp.floating, jnp.integer, jnp.bool_)):
        raise TypeError(f"{requirement}, got dtype {arr.dtype}.")
    return arr


def _host_reals(value: Any) -> np.ndarray | None:
    """`value` as a NumPy array of a real dtype that JAX holds, when it is plain numbers
    (not a JAX array); else `None` (`as_real_array` then decides, or explains)."""
    if isinstance(value, jax.Array):
        return None
    try:
        arr = np.asarray(value)
    except Exception:
        return None
    if arr.dtype.kind not in "biuf" or arr.dtype.itemsize > 8:
        return None
    return arr


def _host_values(value: Any, dtype: Any) -> np.ndarray | None:
    """`value` as a NumPy array of `dtype` when it is known at trace time, else `None`."""
    if isinstance(value, jax.core.Tracer):
        return None
    try:
        with np.errstate(all="ignore"):  # a float32 overflow shows up as inf, checked later
            return np.asarray(value).astype(dtype)
    except Exception:  # holds tracers
        return None


def _abbreviated(value: Any, width: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= width else text[: width - 3] + "..."


def _check_volume(lo: np.ndarray, hi: np.ndarray, dtype: Any) -> None:
    """The box volume and its inverse (the uniform density) must be finite and non-zero in `dtype`."""
    with np.errstate(all="ignore"):
        volume = np.prod(hi - lo, dtype=dtype)
        density = np.asarray(1, dtype) / volume
        exact = np.prod(hi.astype(np.float64) - lo.astype(np.float64))
    if not (np.isfinite(volume) and np.isfinite(density) and volume > 0 and density > 0):
        raise ValueError(
            f"`lo` and `hi` span a box whose volume prod(hi - lo) = {float(exact):.3g} "
            f"is not representable in {np.dtype(dtype).name} (it overflows or underflows); "
            "rescale the variables" + ("." if np.dtype(dtype) == np.float64 else (
                " or pass float64 bounds." if jax.config.jax_enable_x64 else
                " or enable float64: jax.config.update('jax_enable_x64', True)."))
        )


def check_callable(f: Any, name: str = "f", arguments: int | None = None) -> Callable:
    """A callable; with `arguments`, one that accepts that many positional arguments
    (checked against its signature when Python can read one)."""
    if not callable(f):
        raise TypeError(f"`{name}` must be callable, got {type(f).__name__}.")
    if arguments is not None:
        try:
            signature = inspect.signature(f)
        except (TypeError, ValueError):  # builtins and some C callables have none
            return f
        try:
            signature.bind(*([None] * arguments))
        except TypeError:
            raise TypeError(
                f"`{name}` must accept {arguments} positional argument"
                f"{'' if arguments == 1 else 's'}, but its signature is {signature}."
            ) from None
    return f
