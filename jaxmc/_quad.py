"""Tensor-product quadrature rules: the machinery behind `jaxmc.quad`."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._checks import check_bounds, check_callable, check_count
from ._integrand import WithArgs, bind, evaluate


# ---------------------------------------------------------------------------
# 1-D reference rules on [0, 1], in float64 numpy at trace time (sizes static).
# Weights sum to 1; the box's volume is applied afterwards.


def _frozen(*arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    for a in arrays:
        a.setflags(write=False)
    return arrays


@functools.lru_cache(maxsize=64)
def _midpoint_rule(n: int) -> tuple[np.ndarray, np.ndarray]:
    t = (np.arange(n, dtype=np.float64) + 0.5) / n
    w = np.full(n, 1.0 / n)
    return _frozen(t, w)


@functools.lru_cache(maxsize=64)
def _trapezoid_rule(n: int) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(n + 1, dtype=np.float64) / n
    w = np.full(n + 1, 1.0 / n)
    w[0] = w[-1] = 0.5 / n
    return _frozen(t, w)


@functools.lru_cache(maxsize=64)
def _simpson_rule(n: int) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(n + 1, dtype=np.float64) / n
    w = np.where(np.arange(n + 1) % 2 == 1, 4.0, 2.0)
    w[0] = w[-1] = 1.0
    return _frozen(t, w / (3.0 * n))


@functools.lru_cache(maxsize=64)
def _gauss_legendre_rule(n: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(n)
    return _frozen((x + 1.0) / 2.0, w / 2.0)


# ---------------------------------------------------------------------------
# Tensor-product evaluation.


def _tensor_rule(
    f: Callable,
    lo: Any,
    hi: Any,
    n: int,
    rule: Callable[[int], tuple[np.ndarray, np.ndarray]],
    *,
    batched: bool,
    chunk: int,
    limit: int,
    even: bool = False,
    args: Any = None,
) -> jax.Array:
    f = check_callable(f, arguments=1 if args is None else 2)
    n = check_count(n, "n")
    if even and n % 2:
        raise ValueError(f"`n` must be even for Simpson's rule (pairs of intervals), got {n}.")
    chunk = check_count(chunk, "chunk")
    if not isinstance(batched, bool):
        raise TypeError(f"`batched` must be a bool, got {type(batched).__name__}.")
    lo, hi = check_bounds(lo, hi)
    scalar = lo.ndim == 0
    d = 1 if scalar else lo.shape[0]

    t_np, w_np = rule(n)
    m = t_np.shape[0]
    total = m**d
    if total > limit:
        raise ValueError(
            f"`n`={n} in d={d} dimensions needs {m}^{d} = {total:,} integrand evaluations, "
            f"more than MAX_EVALUATIONS = {limit:,}. Tensor-product "
            "quadrature scales as n^d (the curse of dimension); lower `n`, or use a Monte "
            "Carlo estimator such as jaxmc.uniform in this dimension."
        )

    # `args` enter as traced arguments (numbers as arrays: see `jaxmc._integrand.bind`).
    args = None if args is None else bind(f, args).args
    return _evaluate_rule(_ByIdentity(f), lo, hi, rule, n, batched, chunk, args)


class _ByIdentity:
    """Wrap `f` as a static `jit` argument compared by identity.

    Integrands may be unhashable (e.g. modules holding arrays); identity keeps
    the compilation cache valid for them and reuses it when the same `f` is
    integrated again.
    """

    __slots__ = ("f",)

    def __init__(self, f: Callable):
        self.f = f

    def __hash__(self) -> int:
        return id(self.f)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, _ByIdentity) and other.f is self.f


# One compilation per call instead of one per primitive in eager mode; sizes
# and the integrand are static, the bounds are traced.
@functools.partial(jax.jit, static_argnums=(0, 3, 4, 5, 6))
def _evaluate_rule(
    wrapped: _ByIdentity,
    lo: jax.Array,
    hi: jax.Array,
    rule: Callable[[int], tuple[np.ndarray, np.ndarray]],
    n: int,
    batched: bool,
    chunk: int,
    args: Any,
) -> jax.Array:
    f = wrapped.f if args is None else WithArgs(wrapped.f, args)
    scalar = lo.ndim == 0
    d = 1 if scalar else lo.shape[0]
    t_np, w_np = rule(n)
    m = t_np.shape[0]
    total = m**d
    dtype = lo.dtype
    nodes = jnp.asarray(t_np, dtype=dtype)
    weights = jnp.asarray(w_np, dtype=dtype)
    lo_v = jnp.reshape(lo, (d,))
    width = jnp.reshape(hi - lo, (d,))
    # Flat index k ↔ digits (i_1, ..., i_d) in base m, the first axis slowest.
    strides = jnp.asarray(m ** np.arange(d - 1, -1, -1), dtype=jnp.int32)
    size = min(chunk, total)
    n_chunks = -(-total // size)

    def block(start: jax.Array) -> jax.Array:
        k = start + jnp.arange(size, dtype=jnp.int32)
        valid = k < total
        # Padding in the last chunk reuses grid point 0 with weight 0, so f is
        # only ever evaluated at grid points.
        k = jnp.where(valid, k, 0)
        digits = (k[:, None] // strides[None, :]) % m  # (size, d)
        x = lo_v[None, :] + width[None, :] * nodes[digits]
        w = jnp.where(valid, jnp.prod(weights[digits], axis=1), 0)
        fx = evaluate(f, x[:, 0] if scalar else x, batched)
        out = jnp.promote_types(fx.dtype, dtype)
        return jnp.tensordot(w.astype(out), fx.astype(out), axes=1)

    if n_chunks == 1:
        acc = block(jnp.zeros((), jnp.int32))
    else:
        starts = jnp.arange(n_chunks, dtype=jnp.int32) * size
        # One partial sum per chunk, summed at the end: float32 stays accurate
        # because no long running sum is carried through the loop.
        acc = jnp.sum(jax.lax.map(block, starts), axis=0)
    volume = jnp.prod(width)
    return volume.astype(acc.dtype) * acc
