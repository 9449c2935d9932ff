r"""Point sets on the unit cube $[0,1)^d$.

Random point sets (`uniform`, `stratified`, `latin_hypercube`) and
low-discrepancy ones (`halton`, `sobol`, `lattice`), optionally randomised so
that every point is marginally uniform on $[0,1)^d$ while the set keeps its
structure; then each randomised point set gives an unbiased estimator. Also
the classic `lcg` generator, a Fisher–Yates `shuffle`, and the `discrepancy`
of a point set.

Sizes (`n`, `d`, `counts`, `skip`) are static Python ints; keys are traced, so
every function works under `jax.jit` and `jax.vmap` over keys. Points come in
the default float dtype (`float64` under `jax_enable_x64`) unless `dtype` is
given.
"""

from __future__ import annotations

import functools
import math
import operator
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from . import _random
from ._checks import check_choice, check_count, check_key


__all__ = [
    "uniform",
    "stratified",
    "latin_hypercube",
    "halton",
    "sobol",
    "lattice",
    "lcg",
    "shuffle",
    "discrepancy",
    "SOBOL_MAX_DIM",
    "LATTICE_MAX_DIM",
]

_DATA = Path(__file__).parent / "_data"


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------


def _float_dtype(dtype: Any) -> np.dtype:
    dt = jnp.dtype(dtype) if dtype is not None else jnp.dtype(jnp.result_type(float))
    if not jnp.issubdtype(dt, jnp.floating):
        raise TypeError(f"`dtype` must be a floating dtype, got {dt}.")
    return dt


def _below_one(dtype: Any) -> float:
    """The largest float of `dtype` below 1 (rounding must never produce 1)."""
    return float(np.nextafter(np.array(1.0, dtype=dtype), np.array(0.0, dtype=dtype)))


def _x64() -> bool:
    return bool(jax.config.read("jax_enable_x64"))


def _uint32_to_unit(x: jax.Array, dtype: np.dtype) -> jax.Array:
    """Map 32-bit integers $x$ to $x / 2^{32}$ in `dtype`, always `< 1`.

    In float64 this is exact; in float32 (24-bit mantissa) the integer is
    truncated to its top 24 bits first, so the result never rounds up to 1.
    """
    if jnp.finfo(dtype).nmant >= 32:
        return x.astype(dtype) * dtype.type(2.0**-32)
    shift = 32 - (jnp.finfo(dtype).nmant + 1)
    return (x >> np.uint32(shift)).astype(dtype) * dtype.type(2.0 ** -(32 - shift))


def _xor_reduce(x: jax.Array, axis: int) -> jax.Array:
    return lax.reduce(x, np.uint32(0), lax.bitwise_xor, (axis,))


def _trailing_zeros(k: int) -> int:
    return (k & -k).bit_length() - 1 if k else 64


def _check_skip(skip: Any) -> int:
    return check_count(skip, "skip", minimum=0)


# --------------------------------------------------------------------------------------
# i.i.d., stratified and Latin hypercube
# --------------------------------------------------------------------------------------


def uniform(key: jax.Array, n: int, d: int, *, dtype=None) -> jax.Array:
    r"""`n` i.i.d. uniform points on $[0,1)^d$.

    **Arguments:**

    - `key`: a PRNG key.
    - `n`, `d`: number of points and dimension (static ints `>= 1`).
    - `dtype`: floating dtype of the result (default: JAX's default float).

    **Returns:** an array of shape `(n, d)`.
    """
    key = check_key(key)
    n = check_count(n, "n")
    d = check_count(d, "d")
    return _uniform(key, n, d, _float_dtype(dtype))


@functools.partial(jax.jit, static_argnames=("n", "d", "dtype"))
def _uniform(key, n, d, dtype):
    return _random.uniform(key, (n, d), dtype)


def _check_counts(counts: Any) -> tuple[int, ...]:
    if isinstance(counts, (int, np.integer)) and not isinstance(counts, bool):
        counts = (counts,)
    if not isinstance(counts, (tuple, list)):
        raise TypeError(
            f"`counts` must be a tuple of positive ints (strata per axis), got "
            f"{type(counts).__name__} {counts!r}."
        )
    if len(counts) == 0:
        raise ValueError("`counts` must not be empty: give the number of strata of every axis.")
    return tuple(check_count(c, f"counts[{i}]") for i, c in enumerate(counts))


@functools.partial(jax.jit, static_argnames=("counts", "dtype"))
def _stratified(key, counts, dtype):
    total = math.prod(counts)
    d = len(counts)
    u = _random.uniform(key, (total, d), dtype)
    i = lax.broadcasted_iota(jnp.int32 if total < 2**31 else jnp.int64, (total,), 0)
    strides = [math.prod(counts[j + 1 :]) for j in range(d)]
    cells = jnp.stack([(i // s) % c for s, c in zip(strides, counts)], axis=1)
    c = jnp.asarray(counts, dtype=dtype)
    return jnp.minimum((cells.astype(dtype) + u) / c, _below_one(dtype))


def stratified(key: jax.Array, counts: tuple[int, ...], *, dtype=None) -> jax.Array:
    r"""Jittered grid: one uniform point in each cell of a `counts[0] × … × counts[d-1]` grid.

    Cell $k = (k_1, \dots, k_d)$ is $\prod_j [k_j / c_j, (k_j+1)/c_j)$ and holds
    the point $x_j = (k_j + U_j)/c_j$ with $U \sim \mathcal U[0,1)^d$ independent
    per cell, so with $N = \prod_j c_j$ points the equal-weight estimator
    $\frac1N\sum f(x_k)$ is the stratified estimator with one sample per stratum
    (lecture §4.2): unbiased, and never worse than plain Monte Carlo.

    **Arguments:**

    - `key`: a PRNG key.
    - `counts`: strata per axis, a non-empty tuple of static ints `>= 1`; `d = len(counts)`.
    - `dtype`: floating dtype of the result.

    **Returns:** an array of shape `(prod(counts), d)`, cells in row-major (C) order
    (the last axis varies fastest).
    """
    key = check_key(key)
    counts = _check_counts(counts)
    return _stratified(key, counts, _float_dtype(dtype))


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
    if _x64():
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
    return jnp.minimum(x, _below_one(dtype))


def latin_hypercube(key: jax.Array, n: int, d: int, *, dtype=None) -> jax.Array:
    r"""Latin hypercube sample: exactly one of `n` points in each of the `n` bins of every axis.

    Axis $j$ gets an independent random permutation $\pi_j$ of
    $\{0, \dots, n-1\}$ and point $i$ is $x_{ij} = (\pi_j(i) + U_{ij})/n$ with
    $U_{ij} \sim \mathcal U[0,1)$ (McKay, Beckman & Conover 1979; PBRT 3rd ed.
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
    return _latin_hypercube(key, n, d, _float_dtype(dtype))


# --------------------------------------------------------------------------------------
# Sobol'
# --------------------------------------------------------------------------------------


@functools.cache
def _sobol_directions() -> np.ndarray:
    """Direction numbers $v_{j,k} = m_{j,k} 2^{32-k}$, uint32 of shape `(SOBOL_MAX_DIM, 32)`.

    Built from the shipped Joe–Kuo primitive polynomials and initial numbers
    $m_{j,k}$ (see `_data/README.md`) by the recurrence
    $v_k = a_1 v_{k-1} \\oplus \\dots \\oplus a_{s-1} v_{k-s+1} \\oplus v_{k-s} \\oplus (v_{k-s} \\gg s)$.
    Dimension 0 is van der Corput, $v_k = 2^{32-k}$.
    """
    with np.load(_DATA / "sobol_joe_kuo.npz") as table:
        poly = np.concatenate([[1], 1 + np.cumsum(table["poly_diff"].astype(np.int64))])
        bits = np.unpackbits(table["m_bits"]).astype(np.int64)
    max_dim = len(poly)
    degree = np.array([int(p).bit_length() - 1 for p in poly])
    # Decode m_k (odd, < 2^k), stored as (m_k >> 1) in k-1 bits, MSB first.
    dims = np.repeat(np.arange(max_dim), degree)
    ks = np.concatenate([np.arange(1, s + 1) for s in degree])
    widths = ks - 1
    starts = np.cumsum(widths) - widths
    t = np.arange(max(1, widths.max()))
    take = t[None, :] < widths[:, None]
    index = np.where(take, starts[:, None] + t[None, :], 0)
    weights = np.where(take, 1 << np.maximum(widths[:, None] - 1 - t[None, :], 0), 0)
    m = np.zeros((max_dim, max(degree)), dtype=np.int64)
    m[dims, ks - 1] = 2 * np.sum(np.where(take, bits[index], 0) * weights, axis=1) + 1

    v = np.zeros((max_dim, 32), dtype=np.uint64)
    v[0] = np.uint64(1) << (np.uint64(31) - np.arange(32, dtype=np.uint64))
    for s in np.unique(degree[1:]):
        rows = np.nonzero(degree == s)[0]
        vs = np.zeros((len(rows), 32), dtype=np.uint64)
        for k in range(1, min(s, 32) + 1):
            vs[:, k - 1] = m[rows, k - 1].astype(np.uint64) << np.uint64(32 - k)
        a = poly[rows]
        for k in range(s + 1, 33):
            new = vs[:, k - 1 - s] ^ (vs[:, k - 1 - s] >> np.uint64(s))
            for j in range(1, s):
                coefficient = ((a >> (s - j)) & 1).astype(bool)
                new = new ^ np.where(coefficient, vs[:, k - 1 - j], np.uint64(0))
            vs[:, k - 1] = new
        v[rows] = vs
    return v.astype(np.uint32)


def _sobol_max_dim() -> int:
    with np.load(_DATA / "sobol_joe_kuo.npz") as table:
        return int(table["max_dim"])


SOBOL_MAX_DIM: int = _sobol_max_dim()
"""Largest dimension `sobol` supports (Joe–Kuo `new-joe-kuo-6.21201`, first 4096 rows)."""


def _xor_combine(codes: jax.Array, v: jax.Array, nbits: int) -> jax.Array:
    """$\\bigoplus_{j < nbits} [\\text{bit } j \\text{ of code}]\\, v_j$ for each code: `(m,) x (d, 32) -> (m, d)`.

    Written as a reduction, which XLA materialises: a chain of XORs would be fused
    into (and recomputed by) every consumer.
    """
    if nbits == 0:
        return jnp.zeros((codes.shape[0], v.shape[0]), jnp.uint32)
    j = jnp.arange(nbits, dtype=jnp.uint32)
    bits = ((codes[:, None] >> j[None, :]) & np.uint32(1)).astype(bool)
    terms = jnp.where(bits[:, None, :], v[None, :, :nbits], np.uint32(0))
    return _xor_reduce(terms, axis=2)


def _gray(i: jax.Array) -> jax.Array:
    return i ^ (i >> np.uint32(1))


def _sobol_uint32(v: jax.Array, shift: jax.Array, n: int, skip: int) -> jax.Array:
    """Sobol' points `skip .. skip+n-1` as 32-bit integers, shape `(n, d)`.

    Point $i$ is $\\bigoplus_j g_j(i) v_j$ with $g(i) = i \\oplus (i \\gg 1)$ the Gray
    code of $i$ (SciPy's order). Split $i = h 2^k + l$ with $l < 2^k$; then
    $g(i) = (g(h) \\ll k) \\oplus ((h \\bmod 2) \\ll (k-1)) \\oplus g(l)$ and, by
    linearity, $x_i = A_h \\oplus B_l$: two small tables and one XOR per entry.
    """
    total_bits = max(1, (skip + n - 1).bit_length())
    # Block size 2^k: about sqrt(n), dividing skip so that blocks stay aligned.
    k = min((max(n - 1, 1).bit_length() + 1) // 2, _trailing_zeros(skip), 31)
    size = 1 << k
    blocks = -(-n // size)
    low = _gray(jnp.arange(size, dtype=jnp.uint32))
    table_low = _xor_combine(low, v, k)
    h = jnp.arange(blocks, dtype=jnp.uint32) + np.uint32(skip >> k)
    high = _gray(h) << np.uint32(k)
    if k > 0:
        high = high ^ ((h & np.uint32(1)) << np.uint32(k - 1))
    table_high = _xor_combine(high, v, total_bits) ^ shift[None, :]
    x = table_high[:, None, :] ^ table_low[None, :, :]
    x = x.reshape(blocks * size, v.shape[0])
    return x if blocks * size == n else x[:n]


def _lms_shift(key: jax.Array, v: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Linear matrix scramble + digital shift of direction numbers `v` (uint32 `(d, 32)`).

    Each dimension gets a random $32 \\times 32$ matrix over GF(2), lower triangular
    in digit order (output digit $r$ depends on input digits $1..r$) with unit
    diagonal; as a map on 32-bit words, input bit $b$ goes to
    $c_b = 2^b \\oplus (R_b \\bmod 2^b)$ with $R_b$ random. Then a random 32-bit
    digital shift. Returns `(M v, shift)`.
    """
    d = v.shape[0]
    words = jax.random.bits(key, (d, 33), jnp.uint32)
    r, shift = words[:, :32], words[:, 32]
    b = jnp.arange(32, dtype=jnp.uint32)
    diagonal = jnp.left_shift(np.uint32(1), b)
    columns = diagonal | (r & (diagonal - np.uint32(1)))
    bits = ((v[:, :, None] >> b[None, None, :]) & np.uint32(1)).astype(bool)
    scrambled = _xor_reduce(jnp.where(bits, columns[:, None, :], np.uint32(0)), axis=2)
    return scrambled, shift


@functools.partial(jax.jit, static_argnames=("n", "skip", "dtype"))
def _sobol_plain(v, n, skip, dtype):
    shift = jnp.zeros((v.shape[0],), jnp.uint32)
    return _uint32_to_unit(_sobol_uint32(v, shift, n, skip), dtype)


@functools.partial(jax.jit, static_argnames=("n", "skip", "dtype"))
def _sobol_scrambled(key, v, n, skip, dtype):
    v, shift = _lms_shift(key, v)
    return _uint32_to_unit(_sobol_uint32(v, shift, n, skip), dtype)


def sobol(n: int, d: int, *, key: jax.Array | None = None, skip: int = 0, dtype=None) -> jax.Array:
    r"""Sobol' points `skip, …, skip + n - 1`, optionally scrambled.

    A base-2 digital sequence (Sobol' 1967) with Joe–Kuo direction numbers
    (`new-joe-kuo-6.21201`, the table SciPy uses). With 32-bit direction numbers
    $v_{j,1..32}$ for dimension $j$ and the Gray code $g(i) = i \oplus (i \gg 1)$,

    $$x_{ij} = 2^{-32} \bigoplus_{k:\ \text{bit } k \text{ of } g(i) \text{ set}} v_{j,k},$$

    computed directly (no sequential recurrence) with uint32 XORs, so point $i$ is
    the same whatever `n`, and `sobol(n, d, skip=s)` equals rows `s…s+n-1` of a longer
    call. Unscrambled, the first point is 0 and the points equal
    `scipy.stats.qmc.Sobol(d, scramble=False)` after `fast_forward(skip)`. The
    first $2^m$ points form a $(t, m, d)$-net: every 1-D projection has exactly
    one point in each interval $[k 2^{-m}, (k+1) 2^{-m})$.

    With `key`, the directions are scrambled by a random linear matrix scramble
    and a random digital shift (LMS + shift, Matoušek 1998; as SciPy's
    `scramble=True`): the net properties are kept and each point is uniform on
    the $2^{-32}$ grid of $[0,1)^d$. Use powers of two for `n`.

    **Arguments:**

    - `n`: number of points (static int `>= 1`); `skip + n <= 2**32`.
    - `d`: dimension, `1 <= d <= SOBOL_MAX_DIM` (4096).
    - `key`: a PRNG key to scramble, or `None` for the deterministic sequence.
    - `skip`: index of the first point (static int `>= 0`).
    - `dtype`: floating dtype of the result (float32 keeps the top 24 bits).

    **Returns:** an array of shape `(n, d)` in $[0,1)^d$.

    !!! Example

        ```python
        x = jaxmc.points.sobol(1024, 3, key=jax.random.key(0))
        ```
    """
    n = check_count(n, "n")
    d = check_count(d, "d")
    skip = _check_skip(skip)
    if d > SOBOL_MAX_DIM:
        raise ValueError(f"`d` must be <= {SOBOL_MAX_DIM} for `sobol`, got {d}.")
    if n + skip > 2**32:
        raise ValueError(
            f"`skip + n` must be <= 2**32 (32-bit direction numbers), got skip={skip}, n={n}."
        )
    dtype = _float_dtype(dtype)
    v = jnp.asarray(_sobol_directions()[:d])
    if key is None:
        return _sobol_plain(v, n, skip, dtype)
    return _sobol_scrambled(check_key(key), v, n, skip, dtype)


# --------------------------------------------------------------------------------------
# Halton
# --------------------------------------------------------------------------------------


@functools.cache
def _primes(d: int) -> tuple[int, ...]:
    """The first `d` primes."""
    limit = max(16, int(d * (math.log(d + 1) + math.log(math.log(d + 2)) + 2)))
    while True:
        sieve = np.ones(limit + 1, dtype=bool)
        sieve[:2] = False
        for p in range(2, int(limit**0.5) + 1):
            if sieve[p]:
                sieve[p * p :: p] = False
        primes = np.nonzero(sieve)[0]
        if len(primes) >= d:
            return tuple(int(p) for p in primes[:d])
        limit *= 2


def _digits(count: int, base: int) -> int:
    """Number of base-`base` digits of `count - 1` (at least 1)."""
    k, top = 1, base
    while top < count:
        k, top = k + 1, top * base
    return k


def _halton_groups(bases: tuple[int, ...], count: int) -> list[tuple[int, int, int]]:
    """Consecutive runs `(start, stop, digits)` of dimensions needing the same digit count."""
    groups: list[tuple[int, int, int]] = []
    for j, b in enumerate(bases):
        k = _digits(count, b)
        if groups and groups[-1][2] == k:
            groups[-1] = (groups[-1][0], j + 1, k)
        else:
            groups.append((j, j + 1, k))
    return groups


def _digit_step(q, b, inv_b, exact_float):
    """`(q mod b, q // b)`, by a multiply where possible: CPUs have no vector integer division.

    In float64 the rounded quotient is exact for q < 2^50. For int32 `q` below
    2^24 (exact in float32; `inv_b` given) the float32 estimate is off by at most
    one, and the integer remainder corrects it. Larger int32 `q`: integer division.
    """
    if exact_float:
        quotient = jnp.floor((q + 0.5) * inv_b)
        return q - quotient * b, quotient
    if inv_b is None:
        return q % b, q // b
    quotient = jnp.floor(q.astype(jnp.float32) * inv_b).astype(jnp.int32)
    remainder = q - quotient * b
    low, high = remainder < 0, remainder >= b
    quotient = quotient - low.astype(jnp.int32) + high.astype(jnp.int32)
    remainder = remainder + jnp.where(low, b, 0) - jnp.where(high, b, 0)
    return remainder, quotient


def _halton_layout(bases, count, dtype):
    """Static layout of the per-digit tables: `(base, used digits, total digits, offset)`."""
    resolution = jnp.finfo(dtype).nmant + 1
    layout = []
    offset = 0
    for b in bases:
        used = _digits(count, b)  # digits that vary over the points
        total = max(used, math.ceil(resolution / math.log2(b)))  # digits to the float resolution
        layout.append((b, used, total, offset))
        offset += used * b
    return layout, offset


def _digit_weights(b: int, k: int) -> np.ndarray:
    """SciPy's digit weights $r_0 = 1/b$, $r_{t+1} = r_t / b$ (same rounding)."""
    r = np.empty(k)
    r[0] = 1.0 / b
    for t in range(1, k):
        r[t] = r[t - 1] / b
    return r


@functools.partial(jax.jit, static_argnames=("n", "d", "skip", "dtype"))
def _halton(key, n, d, skip, dtype):
    bases = _primes(d)
    layout, size = _halton_layout(bases, skip + n, dtype)
    exact_float = _x64()
    acc = jnp.float64 if exact_float else dtype
    local = np.concatenate([np.tile(np.arange(b), u) for b, u, _, _ in layout])
    weight = np.concatenate([np.repeat(_digit_weights(b, u), b) for b, u, _, _ in layout])
    # Unscrambled in single precision, digit values are products: cheaper than a gather.
    tabulated = key is not None or exact_float
    if key is None:
        # Digit values a * r_t tabulated in float64 by NumPy: a product computed in the
        # kernel could be fused into an FMA with the running sum, and differ from SciPy
        # in the last bit.
        table = jnp.asarray(local * weight, acc) if tabulated else None
        tail = jnp.zeros((d,), acc)
    else:
        width = max(1, max(total - u for _, u, total, _ in layout))
        # One draw for everything (each separate random call costs compile time).
        words = jax.random.bits(key, (2 * size + d * width,), jnp.uint32)
        # All permutations in one segmented sort: segment (j, t) holds 0..b_j-1 sorted by
        # (segment, two random 32-bit words), so each segment is a uniform permutation.
        segment = np.concatenate(
            [np.repeat(np.arange(o, o + u * b, b), b) for b, u, _, o in layout]
        )
        _, _, _, perm = lax.sort(
            (
                jnp.asarray(segment, jnp.int32),
                words[:size],
                words[size : 2 * size],
                jnp.asarray(local, jnp.int32),
            ),
            num_keys=3,
        )
        table = perm.astype(acc) * jnp.asarray(weight, acc)
        # Digits beyond those of the largest index are 0 for every point; their permuted
        # values pi_t(0) are independent uniform digits, so draw them directly.
        weights = np.zeros((d, width))
        for j, (b, u, total, _) in enumerate(layout):
            weights[j, : total - u] = _digit_weights(b, total)[u:]
        # Uniform digits floor(b U): bias at most b 2^-24 per digit, far below the weight
        # of these trailing digits.
        base = jnp.asarray([b for b, _, _, _ in layout], acc)[:, None]
        unit = _uint32_to_unit(words[2 * size :].reshape(d, width), jnp.dtype(acc))
        digits = jnp.minimum(jnp.floor(unit * base), base - 1)
        tail = jnp.sum(digits * jnp.asarray(weights, acc), axis=1)

    work = jnp.float64 if exact_float else jnp.int32
    index = jnp.arange(skip, skip + n, dtype=work)[:, None]
    columns = []
    for start, stop, k in _halton_groups(bases, skip + n):
        b_np = np.asarray(bases[start:stop])
        offsets = np.asarray([layout[j][3] for j in range(start, stop)])
        b = jnp.asarray(b_np, dtype=work)[None, :]
        # Without x64, indices at or above 2^24 are not exact in float32: integer division.
        multiply = exact_float or skip + n <= 2**24
        inv_b = jnp.asarray(1.0 / b_np, work if exact_float else jnp.float32)[None, :]
        inv_b = inv_b if multiply else None
        q = jnp.broadcast_to(index, (n, stop - start))
        x = jnp.broadcast_to(tail[start:stop][None, :], (n, stop - start))
        for t in range(k):
            digit, q = _digit_step(q, b, inv_b, exact_float)
            if tabulated:
                where = digit.astype(jnp.int32) + jnp.asarray(offsets + t * b_np, jnp.int32)
                x = x + table[where]
            else:
                r_t = np.asarray([_digit_weights(int(bj), t + 1)[t] for bj in b_np])
                x = x + digit.astype(acc) * jnp.asarray(r_t, acc)[None, :]
        columns.append(x)
    x = jnp.concatenate(columns, axis=1) if len(columns) > 1 else columns[0]
    return jnp.minimum(x.astype(dtype), _below_one(dtype))


def halton(n: int, d: int, *, key: jax.Array | None = None, skip: int = 0, dtype=None) -> jax.Array:
    r"""Halton points `skip, …, skip + n - 1`, optionally randomised by digit permutations.

    Dimension $j$ is the van der Corput sequence in the $j$-th prime base $b_j$
    (2, 3, 5, …): if $i = \sum_t a_t b_j^t$, then $x_{ij} = \phi_{b_j}(i) =
    \sum_t a_t b_j^{-t-1}$ (Halton 1960; PBRT §7.4). Index 0 (the origin) comes
    first; unscrambled points equal `scipy.stats.qmc.Halton(d, scramble=False)`
    after `fast_forward(skip)` (same order of floating-point operations).

    With `key`, each digit position $t$ of each dimension gets its own uniformly
    random permutation $\pi_{j,t}$ of $\{0, \dots, b_j - 1\}$, applied to every
    digit including the infinitely many leading zeros of $i$ (truncated at the
    float resolution): $x_{ij} = \sum_t \pi_{j,t}(a_t) b_j^{-t-1}$ — SciPy's
    `scramble=True` construction (random digit permutations, Owen 2017 "A
    randomized Halton algorithm in R"). Digits of a fixed point are then
    independent and uniform, so each point is marginally uniform, while every
    elementary interval keeps its count.

    **Arguments:**

    - `n`: number of points (static int `>= 1`).
    - `d`: dimension (static int `>= 1`); large `d` means large prime bases and
      poor projections — prefer `sobol` beyond a few dozen dimensions.
    - `key`: a PRNG key to randomise, or `None`.
    - `skip`: index of the first point (static int `>= 0`).
    - `dtype`: floating dtype of the result.

    **Returns:** an array of shape `(n, d)` in $[0,1)^d$.
    """
    n = check_count(n, "n")
    d = check_count(d, "d")
    skip = _check_skip(skip)
    limit = 2**50 if _x64() else 2**31 - 1
    if n + skip > limit:
        raise ValueError(
            f"`skip + n` must be <= {limit} for `halton`"
            + ("" if _x64() else " without jax_enable_x64")
            + f", got skip={skip}, n={n}."
        )
    dtype = _float_dtype(dtype)
    return _halton(None if key is None else check_key(key), n, d, skip, dtype)


# --------------------------------------------------------------------------------------
# rank-1 lattice
# --------------------------------------------------------------------------------------


@functools.cache
def _lattice_vector() -> np.ndarray:
    lines = (_DATA / "lattice_kuo_order2.txt").read_text().splitlines()
    return np.array([int(s) for s in lines if s and not s.startswith("#")], dtype=np.int64)


LATTICE_MAX_DIM: int = 100
"""Largest dimension `lattice` supports (the shipped generating vector has 100 components)."""


@functools.partial(jax.jit, static_argnames=("n", "d", "dtype"))
def _lattice(key, n, d, dtype):
    z = _lattice_vector()[:d] % n
    if n & (n - 1) == 0:
        # i z mod 2^32 wraps, and 2^32 is a multiple of n.
        i = jnp.arange(n, dtype=jnp.uint32)[:, None]
        k = (i * jnp.asarray(z, jnp.uint32)[None, :]) & np.uint32(n - 1)
    elif _x64():
        i = jnp.arange(n, dtype=jnp.int64)[:, None]
        k = (i * jnp.asarray(z, jnp.int64)[None, :]) % n
    else:
        i = jnp.arange(n, dtype=jnp.uint32)[:, None]
        k = (i * jnp.asarray(z, jnp.uint32)[None, :]) % np.uint32(n)
    acc = np.dtype(jnp.float64 if _x64() else dtype)
    x = k.astype(acc) / acc.type(n)  # XLA may use a reciprocal: exact only for powers of two
    if key is not None:
        x = x + jax.random.uniform(key, (d,), dtype=acc)[None, :]
        x = jnp.where(x >= 1, x - 1, x)
    return jnp.minimum(x.astype(dtype), _below_one(dtype))


def lattice(n: int, d: int, *, key: jax.Array | None = None, dtype=None) -> jax.Array:
    r"""Rank-1 lattice $x_i = \{ i z / n \}$, $i = 0, \dots, n-1$; with `key`, randomly shifted.

    The generating vector $z$ is the order-2 embedded (extensible) lattice
    sequence `lattice-32001-1024-1048576.3600` of Cools, Kuo & Nuyens (2006),
    constructed by component-by-component search for $n = 2^{10}, \dots, 2^{20}$
    (first 100 components shipped; see `_data/README.md`). For powers of two the
    point sets are nested, for other `n` it is still a valid lattice but its
    quality is not guaranteed.

    With `key`, a single uniform shift $\Delta \sim \mathcal U[0,1)^d$ is added
    modulo 1, $x_i = \{ i z / n + \Delta \}$ (Cranley & Patterson 1976): each point
    is uniform on $[0,1)^d$ and the lattice structure is kept.

    **Arguments:**

    - `n`: number of points (static int `>= 1`; a power of two up to `2**20` is best).
      Non-powers of two above `2**16` need `jax_enable_x64`.
    - `d`: dimension, `1 <= d <= LATTICE_MAX_DIM` (100).
    - `key`: a PRNG key for the random shift, or `None`.
    - `dtype`: floating dtype of the result.

    **Returns:** an array of shape `(n, d)` in $[0,1)^d$.
    """
    n = check_count(n, "n")
    d = check_count(d, "d")
    if d > LATTICE_MAX_DIM:
        raise ValueError(f"`d` must be <= {LATTICE_MAX_DIM} for `lattice`, got {d}.")
    if n > 2**32:
        raise ValueError(f"`n` must be <= 2**32 for `lattice`, got {n}.")
    if n & (n - 1) and not _x64() and n > 2**16:
        raise ValueError(
            f"`n` = {n} is not a power of two; without jax_enable_x64 only n <= 2**16 "
            "is supported (the products i*z need 64 bits)."
        )
    if key is not None:
        key = check_key(key)
    return _lattice(key, n, d, _float_dtype(dtype))


# --------------------------------------------------------------------------------------
# linear congruential generator
# --------------------------------------------------------------------------------------


def _check_lcg_int(value: Any, name: str, low: int, high: int) -> int:
    if isinstance(value, bool):
        raise TypeError(f"`{name}` must be an int, got a bool.")
    try:
        value = operator.index(value)
    except TypeError:
        raise TypeError(f"`{name}` must be a Python int, got {type(value).__name__}.") from None
    if not low <= value < high:
        raise ValueError(f"`{name}` must be in [{low}, {high}), got {value}.")
    return value


@functools.partial(jax.jit, static_argnames=("n", "a", "c", "m", "dtype"))
def _lcg(seed, n, a, c, m, dtype):
    if m & (m - 1) == 0:
        # m | 2^32: uint32 wrap-around arithmetic is exact mod m.
        work = jnp.uint32

        def mulmod(x, y):
            return x * y

        def addmod(x, y):
            return x + y

        mask = np.uint32(m - 1)
        reduce = (lambda x: x & mask) if m < 2**32 else (lambda x: x)
    else:
        work = jnp.uint64 if _x64() else jnp.uint32  # m <= 2^16 without x64 (checked)
        modulus = np.dtype(work).type(m)

        def mulmod(x, y):
            return (x * y) % modulus

        def addmod(x, y):
            return (x + y) % modulus

        def reduce(x):
            return x

    # x_i = A_i x_0 + C_i: the affine maps x -> a x + c compose associatively,
    # (A2, C2) o (A1, C1) = (A2 A1, A2 C1 + C2), so all prefixes come from one scan.
    a_arr = jnp.full((n,), a, dtype=work)
    c_arr = jnp.full((n,), c, dtype=work)

    def compose(first, second):
        a1, c1 = first
        a2, c2 = second
        return reduce(mulmod(a2, a1)), reduce(addmod(mulmod(a2, c1), c2))

    big_a, big_c = lax.associative_scan(compose, (a_arr, c_arr))
    x0 = jnp.asarray(seed).astype(work)
    x = reduce(addmod(mulmod(big_a, x0), big_c))
    acc = np.dtype(jnp.float64 if _x64() else dtype)
    return jnp.minimum((x.astype(acc) / acc.type(m)).astype(dtype), _below_one(dtype))


def lcg(
    seed: int | jax.Array,
    n: int,
    *,
    a: int = 1664525,
    c: int = 1013904223,
    m: int = 2**32,
    dtype=None,
) -> jax.Array:
    r"""Linear congruential generator $x_{i+1} = (a x_i + c) \bmod m$, returning $x_1/m, \dots, x_n/m$.

    The defaults are the *Numerical Recipes* constants (Knuth, TAOCP vol. 2 §3.2).
    The $n$ states are computed in parallel: $x_i = A_i x_0 + C_i \pmod m$ where
    the affine maps $x \mapsto a x + c$ compose associatively, so
    `lax.associative_scan` gives all $(A_i, C_i)$ in $O(\log n)$ depth.

    Moduli that divide $2^{32}$ use exact uint32 wrap-around arithmetic. Other
    moduli need products below $2^{64}$: with `jax_enable_x64` any
    $m \le 2^{32}$ works; without it only $m \le 2^{16}$ (products fit in uint32).
    This is a teaching generator — its low bits and lattice structure are poor;
    use `jax.random` for real work.

    **Arguments:**

    - `seed`: the state $x_0$, an int in $[0, m)$ (may be a traced integer array).
    - `n`: number of outputs (static int `>= 1`).
    - `a`, `c`, `m`: multiplier, increment and modulus (static ints, $0 \le a, c < m$,
      $2 \le m \le 2^{32}$).
    - `dtype`: floating dtype of the result (values are clipped below 1 in float32).

    **Returns:** an array of shape `(n,)` in $[0, 1)$.
    """
    n = check_count(n, "n")
    m = _check_lcg_int(m, "m", 2, 2**32 + 1)
    a = _check_lcg_int(a, "a", 0, m)
    c = _check_lcg_int(c, "c", 0, m)
    if m & (m - 1) and not _x64() and m > 2**16:
        raise ValueError(
            f"`m` = {m} is not a power of two; without jax_enable_x64 only m <= 2**16 "
            "is supported (the products need 64 bits)."
        )
    if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
        seed = _check_lcg_int(seed, "seed", 0, m)
        seed = np.uint64(seed) if _x64() else np.uint32(seed)
    else:
        seed = jnp.asarray(seed)
        if seed.shape != () or not jnp.issubdtype(seed.dtype, jnp.integer):
            raise TypeError(
                f"`seed` must be an int or an integer scalar array, got {seed.dtype} {seed.shape}."
            )
    return _lcg(seed, n, a, c, m, _float_dtype(dtype))


# --------------------------------------------------------------------------------------
# Fisher–Yates shuffle
# --------------------------------------------------------------------------------------


@jax.jit
def _fisher_yates(key, x):
    n = x.shape[0]
    # j_i uniform on {0..i} for i = n-1 .. 1 (drawn up front; the loop only swaps).
    upper = jnp.arange(1, n + 1, dtype=jnp.int32)
    js = jax.random.randint(key, (n,), 0, upper, dtype=jnp.int32)

    def body(t, perm):
        i = n - 1 - t
        j = js[i]
        pi, pj = perm[i], perm[j]
        return perm.at[i].set(pj).at[j].set(pi)

    perm = lax.fori_loop(0, n - 1, body, jnp.arange(n, dtype=jnp.int32))
    return jnp.take(x, perm, axis=0)


def shuffle(key: jax.Array, x: jax.Array) -> jax.Array:
    r"""Shuffle `x` along axis 0 with the Fisher–Yates algorithm.

    For $i = n-1, \dots, 1$: draw $j$ uniform on $\{0, \dots, i\}$ and swap
    entries $i$ and $j$ (Durstenfeld 1964; Knuth's Algorithm P). Each of the $n!$
    permutations has probability $1/n!$. The swaps run in a `lax.fori_loop` on
    an index array (so the loop is $O(n)$ whatever the row size), then the rows are
    gathered once.

    **Arguments:**

    - `key`: a PRNG key.
    - `x`: an array with at least one axis.

    **Returns:** an array like `x` with its rows permuted.
    """
    key = check_key(key)
    x = jnp.asarray(x)
    if x.ndim == 0:
        raise ValueError("`x` must have at least one axis to shuffle, got a scalar.")
    if x.shape[0] >= 2**31:
        raise ValueError(f"`x` must have fewer than 2**31 rows, got {x.shape[0]}.")
    if x.shape[0] <= 1:
        return x
    return _fisher_yates(key, x)


# --------------------------------------------------------------------------------------
# discrepancy
# --------------------------------------------------------------------------------------


def _pairwise_sum(x: jax.Array, kernel) -> jax.Array:
    """$\\sum_{i,j} \\prod_k \\text{kernel}(x_{ik}, x_{jk})$ in row blocks of bounded memory."""
    n, d = x.shape
    block = max(1, min(n, 2**22 // max(1, n * d)))
    blocks = -(-n // block)
    padded = jnp.concatenate([x, jnp.zeros((blocks * block - n, d), x.dtype)], axis=0)
    valid = jnp.arange(blocks * block) < n

    def one(args):
        rows, mask = args
        terms = jnp.prod(kernel(rows[:, None, :], x[None, :, :]), axis=2)
        return jnp.sum(jnp.where(mask[:, None], terms, 0))

    parts = lax.map(one, (padded.reshape(blocks, block, d), valid.reshape(blocks, block)))
    return jnp.sum(parts)


@functools.partial(jax.jit, static_argnames=("method",))
def _discrepancy(x, method):
    n, d = x.shape
    if method == "CD":
        a = jnp.abs(x - 0.5)
        first = (13.0 / 12.0) ** d
        second = 2.0 / n * jnp.sum(jnp.prod(1 + 0.5 * a - 0.5 * a**2, axis=1))
        third = (
            _pairwise_sum(
                x,
                lambda u, v: (
                    1 + 0.5 * jnp.abs(u - 0.5) + 0.5 * jnp.abs(v - 0.5) - 0.5 * jnp.abs(u - v)
                ),
            )
            / n**2
        )
        return first - second + third
    first = 3.0 ** (-d)
    second = 2.0 ** (1 - d) / n * jnp.sum(jnp.prod(1 - x**2, axis=1))
    third = _pairwise_sum(x, lambda u, v: 1 - jnp.maximum(u, v)) / n**2
    return jnp.sqrt(first - second + third)


def discrepancy(x: jax.Array, *, method: str = "CD") -> jax.Array:
    r"""Discrepancy of a point set `x` of shape `(n, d)` in $[0,1]^d$ (lower is more uniform).

    - `"CD"`, the centred $L_2$ discrepancy (Hickernell 1998), **squared** as in SciPy:
      $$\left(\tfrac{13}{12}\right)^d - \tfrac{2}{n}\sum_i \prod_k \left(1 + \tfrac12|x_{ik} - \tfrac12| - \tfrac12|x_{ik} - \tfrac12|^2\right) + \tfrac{1}{n^2}\sum_{i,j}\prod_k\left(1 + \tfrac12|x_{ik}-\tfrac12| + \tfrac12|x_{jk}-\tfrac12| - \tfrac12|x_{ik}-x_{jk}|\right).$$
    - `"L2-star"`, the $L_2$-star discrepancy (Warnock's formula), as in SciPy:
      $$\left(3^{-d} - \tfrac{2^{1-d}}{n}\sum_i\prod_k (1 - x_{ik}^2) + \tfrac1{n^2}\sum_{i,j}\prod_k (1 - \max(x_{ik}, x_{jk}))\right)^{1/2}.$$

    Both equal `scipy.stats.qmc.discrepancy(x, method=...)`. The double sum costs
    $O(n^2 d)$ and is evaluated in row blocks of bounded memory.

    **Arguments:**

    - `x`: points, shape `(n, d)`.
    - `method`: `"CD"` or `"L2-star"`.

    **Returns:** a scalar.
    """
    method = check_choice(method, "method", ("CD", "L2-star"))
    x = jnp.asarray(x)
    if x.ndim != 2 or x.shape[0] < 1 or x.shape[1] < 1:
        raise ValueError(f"`x` must have shape (n, d) with n, d >= 1, got {x.shape}.")
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return _discrepancy(x, method)
