r"""Random point sets: i.i.d. `uniform`, the jittered grid `stratified`, and `latin_hypercube`."""

from __future__ import annotations

import functools
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .. import _random
from .._checks import check_count, check_key
from ._common import float_dtype, open_unit, x64_enabled


def uniform(key: jax.Array, n: int, d: int, *, dtype=None) -> jax.Array:
    r"""`n` i.i.d. uniform points on the open cube $(0,1)^d$ (see `_random.uniform`).

    **Arguments:**

    - `key`: a PRNG key.
    - `n`, `d`: number of points and dimension (static ints `>= 1`).
    - `dtype`: floating dtype of the result (default: JAX's default float).

    **Returns:** an array of shape `(n, d)`.
    """
    key = check_key(key)
    n = check_count(n, "n")
    d = check_count(d, "d")
    return _uniform(key, n, d, float_dtype(dtype))


@functools.partial(jax.jit, static_argnames=("n", "d", "dtype"))
def _uniform(key, n, d, dtype):
    return _random.uniform(key, (n, d), dtype)


def check_counts(
    counts: Any, d: int | None = None, *, scalar: bool = False, name: str = "counts"
) -> tuple[int, ...]:
    """Strata per axis: a tuple of static ints `>= 1`, one per axis.

    - Alone (a jittered grid, `d = len(counts)`): any non-empty tuple or list; an
      int is one axis.
    - With `d` (bounds of shape `(d,)`): exactly `d` entries; a bare int only when
      `d == 1`.
    - With `scalar=True` (scalar bounds): an int or a 1-tuple.
    """
    if scalar:
        if isinstance(counts, (tuple, list)):
            if len(counts) != 1:
                raise ValueError(
                    f"`{name}` must be an int (or a 1-tuple) for scalar bounds, got {counts!r}."
                )
            counts = counts[0]
        return (check_count(counts, name),)
    if d is None:
        if isinstance(counts, (int, np.integer)) and not isinstance(counts, bool):
            counts = (counts,)
        if not isinstance(counts, (tuple, list)):
            raise TypeError(
                f"`{name}` must be a tuple of positive ints (strata per axis), got "
                f"{type(counts).__name__} {counts!r}."
            )
        if len(counts) == 0:
            raise ValueError(
                f"`{name}` must not be empty: give the number of strata of every axis."
            )
    else:
        if not isinstance(counts, (tuple, list)):
            if d == 1:
                try:
                    return (check_count(counts, name),)
                except TypeError:
                    pass
            raise TypeError(
                f"`{name}` must be a tuple of {d} ints (strata per axis) for bounds of shape "
                f"({d},), got {type(counts).__name__} {counts!r}."
            )
        if len(counts) != d:
            raise ValueError(
                f"`{name}` must have one entry per dimension ({d}), got {len(counts)}: {counts!r}."
            )
    return tuple(check_count(c, f"{name}[{j}]") for j, c in enumerate(counts))


@functools.partial(jax.jit, static_argnames=("counts", "dtype"))
def _stratified(key, counts, dtype):
    total = math.prod(counts)
    d = len(counts)
    u = _random.uniform(key, (total, d), dtype)
    i = lax.broadcasted_iota(jnp.int32 if total < 2**31 else jnp.int64, (total,), 0)
    strides = [math.prod(counts[j + 1 :]) for j in range(d)]
    cells = jnp.stack([(i // s) % c for s, c in zip(strides, counts)], axis=1)
    c = jnp.asarray(counts, dtype=dtype)
    return open_unit((cells.astype(dtype) + u) / c)


def stratified(key: jax.Array, counts: tuple[int, ...], *, dtype=None) -> jax.Array:
    r"""Jittered grid: one uniform point in each cell of a `counts[0] × … × counts[d-1]` grid.

    Cell $k = (k_1, \dots, k_d)$ is $\prod_j [k_j / c_j, (k_j+1)/c_j)$ and holds
    the point $x_j = (k_j + U_j)/c_j$ with $U \sim \mathcal U(0,1)^d$ independent
    per cell, so with $N = \prod_j c_j$ points the equal-weight estimator
    $\frac1N\sum f(x_k)$ is the stratified estimator with one sample per stratum
    (Owen, *Monte Carlo theory, methods and examples*, ch. 8; PBRT 3rd ed. §13.8.1): unbiased,
    and never worse than plain Monte Carlo.

    **Arguments:**

    - `key`: a PRNG key.
    - `counts`: strata per axis, a non-empty tuple of static ints `>= 1`; `d = len(counts)`.
    - `dtype`: floating dtype of the result.

    **Returns:** an array of shape `(prod(counts), d)`, cells in row-major (C) order
    (the last axis varies fastest).
    """
    key = check_key(key)
    counts = check_counts(counts)
    return _stratified(key, counts, float_dtype(dtype))


def _random_permutations(key: jax.Array, d: int, n: int) -> jax.Array:
    """`d` independent random permutations of `0..n-1`, int32 of shape `(d, n)`.

    Sorting i.i.d. random keys gives a uniform permutation. XLA sorts a single
    integer array much faster than keys with a payload, so the index rides in the
    low `L = bit_length(n - 1)` bits of the key and the sorted keys' low bits are
    the permutation; ties of the random high bits are broken by index. With x64,
    one sort of 64-bit keys (`64 - L` random bits; tie probability
    $\approx n^2 2^{L-65}$). Without x64, each 32-bit round has only `32 - L`
    random bits, i.e. it is an inverse riffle shuffle with $2^{32-L}$ piles; `R`
    rounds compose to one with $2^{R(32-L)}$ piles, within total variation
    $\approx n^2 2^{-R(32-L)}$ of uniform (Bayer & Diaconis 1992), and `R` is
    chosen to make that below $2^{-24}$.
    """
    bits = max(1, (n - 1).bit_length())
    iota = lax.broadcasted_iota(jnp.uint32, (d, n), 1)
    if x64_enabled():
        mask = np.uint64((1 << bits) - 1)
        r = lax.bitcast_convert_type(_random.bits(key, (d, n, 2)), jnp.uint64)
        packed = jnp.sort((r & ~mask) | iota.astype(jnp.uint64), axis=1)
        return (packed & mask).astype(jnp.int32)
    free = 32 - bits
    if free < 8:
        k1, k2 = jax.random.split(key)
        keys = (_random.bits(k1, (d, n)), _random.bits(k2, (d, n)))
        return lax.sort((*keys, iota.astype(jnp.int32)), dimension=1, num_keys=2)[-1]
    mask = np.uint32((1 << bits) - 1)
    rounds = -(-(2 * bits + 24) // free)
    perm = iota.astype(jnp.int32)
    for k in jax.random.split(key, rounds):
        r = _random.bits(k, (d, n))
        order = (jnp.sort((r & ~mask) | iota, axis=1) & mask).astype(jnp.int32)
        perm = jnp.take_along_axis(perm, order, axis=1)
    return perm


# Above this many bins, LHS permutations come from `_random.permute` instead of sorts.
_LHS_SORT_MAX = 2**16


def _lhs_bins(key: jax.Array, n: int, d: int) -> jax.Array:
    """Bin of point i on axis j, `(n, d)`: exact random permutations up to `_LHS_SORT_MAX` bins."""
    if n <= _LHS_SORT_MAX:
        return _random_permutations(key, d, n).T
    index = lax.broadcasted_iota(jnp.uint32, (n, d), 0)
    axis = lax.broadcasted_iota(jnp.uint32, (n, d), 1)
    return _random.permute(key, index, n, stream=axis)


@functools.partial(jax.jit, static_argnames=("n", "d", "dtype"))
def _latin_hypercube(key, n, d, dtype):
    key_perm, key_jitter = jax.random.split(key)
    bins = _lhs_bins(key_perm, n, d)
    u = _random.uniform(key_jitter, (n, d), dtype)
    x = (bins.astype(dtype) + u) * dtype.type(1.0 / n)
    return open_unit(x)


def latin_hypercube(key: jax.Array, n: int, d: int, *, dtype=None) -> jax.Array:
    r"""Latin hypercube sample: exactly one of `n` points in each of the `n` bins of every axis.

    Axis $j$ gets an independent random permutation $\pi_j$ of
    $\{0, \dots, n-1\}$ and point $i$ is $x_{ij} = (\pi_j(i) + U_{ij})/n$ with
    $U_{ij} \sim \mathcal U(0,1)$ (McKay, Beckman & Conover 1979; PBRT 3rd ed.
    §7.2.3). Each point is marginally uniform on $[0,1)^d$ and every 1-D
    projection is stratified into `n` equal bins, one point per bin.

    Up to $2^{16}$ bins the permutations are exactly uniform (sorts of random
    keys). Beyond, where sorting dominates the cost, they are keyed
    pseudorandom permutations (a Threefry Feistel network with cycle walking, as
    PBRT-v4 permutes its samples, rotated by a uniform offset): each
    $\pi_j(i)$ is still exactly uniform on the bins, so the estimator stays
    unbiased, at $O(nd)$ parallel cost.

    **Arguments:**

    - `key`: a PRNG key.
    - `n`, `d`: number of points and dimension (static ints `>= 1`).
    - `dtype`: floating dtype of the result.

    **Returns:** an array of shape `(n, d)`.
    """
    key = check_key(key)
    n = check_count(n, "n")
    d = check_count(d, "d")
    if n >= 2**31:
        raise ValueError(f"`n` must be < 2**31, got {n}.")
    return _latin_hypercube(key, n, d, float_dtype(dtype))

