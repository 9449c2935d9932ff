r"""Sobol' points: a base-2 digital sequence with Joe–Kuo direction numbers, optionally scrambled."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._checks import check_count, check_key
from ._common import DATA_DIR, check_skip, float_dtype, uint32_to_unit


def _xor_reduce(x: jax.Array, axis: int) -> jax.Array:
    return lax.reduce(x, np.uint32(0), lax.bitwise_xor, (axis,))


def _trailing_zeros(k: int) -> int:
    return (k & -k).bit_length() - 1 if k else 64



@functools.cache
def _sobol_directions() -> np.ndarray:
    """Direction numbers $v_{j,k} = m_{j,k} 2^{32-k}$, uint32 of shape `(SOBOL_MAX_DIM, 32)`.

    Built from the shipped Joe–Kuo primitive polynomials and initial numbers
    $m_{j,k}$ (see `_data/README.md`) by the recurrence
    $v_k = a_1 v_{k-1} \\oplus \\dots \\oplus a_{s-1} v_{k-s+1} \\oplus v_{k-s} \\oplus (v_{k-s} \\gg s)$.
    Dimension 0 is van der Corput, $v_k = 2^{32-k}$.
    """
    with np.load(DATA_DIR / "sobol_joe_kuo.npz") as table:
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
    with np.load(DATA_DIR / "sobol_joe_kuo.npz") as table:
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


def sobol_block(directions: jax.Array, shift: jax.Array, index: jax.Array, log2_size: int) -> jax.Array:
    r"""Block `index` of a (scrambled) Sobol' sequence: points $i\,2^k, \dots, (i+1)\,2^k - 1$, as uint32.

    The block's position `index` may be traced (a loop counter), so a stream can
    walk one sequence block by block: with $k$ = `log2_size`, point
    $i 2^k + l$ is $A_i \oplus B_l$ where $A_i$ combines the directions of the
    high Gray-code bits of the index and $B_l$ the low ones (see
    `_sobol_uint32`); both blocks of a split are aligned, so the points equal
    rows $i 2^k \dots$ of `sobol` with the same directions. Every block of
    $2^k$ points is itself a $(t, k, d)$-net, and the first $2^m$ points of
    the sequence a $(t, m, d)$-net.

    **Arguments:** `directions` (uint32 `(d, 32)`, e.g. from `sobol_scramble`),
    `shift` (uint32 `(d,)`), `index` (int scalar), `log2_size` (static int).

    **Returns:** uint32 array `(2**log2_size, d)`; map to $(0,1)$ with `uint32_to_unit`.
    """
    k_low = (log2_size + 1) // 2  # two tables of about sqrt(2^k) rows each
    size_low, rows = 1 << k_low, 1 << (log2_size - k_low)
    table_low = _xor_combine(_gray(jnp.arange(size_low, dtype=jnp.uint32)), directions, k_low)
    h = jnp.arange(rows, dtype=jnp.uint32) + jnp.asarray(index, jnp.uint32) * np.uint32(rows)
    high = _gray(h) << np.uint32(k_low)
    if k_low > 0:
        high = high ^ ((h & np.uint32(1)) << np.uint32(k_low - 1))
    table_high = _xor_combine(high, directions, 32) ^ shift[None, :]
    x = table_high[:, None, :] ^ table_low[None, :, :]
    return x.reshape(rows * size_low, directions.shape[0])


def sobol_scramble(key: jax.Array, d: int) -> tuple[jax.Array, jax.Array]:
    """Scrambled direction numbers and digital shift of a `d`-dimensional Sobol' sequence.

    The randomisation `sobol(n, d, key=key)` applies (`_lms_shift`), returned for
    `sobol_block`: `(directions (d, 32), shift (d,))`, both uint32.
    """
    return _lms_shift(key, jnp.asarray(_sobol_directions()[:d]))


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
    return uint32_to_unit(_sobol_uint32(v, shift, n, skip), dtype)


@functools.partial(jax.jit, static_argnames=("n", "skip", "dtype"))
def _sobol_scrambled(key, v, n, skip, dtype):
    v, shift = _lms_shift(key, v)
    return uint32_to_unit(_sobol_uint32(v, shift, n, skip), dtype, centred=True)


def sobol(n: int, d: int, *, key: jax.Array | None = None, skip: int = 0, dtype=None) -> jax.Array:
    r"""Sobol' points `skip, …, skip + n - 1`, optionally scrambled.

    A base-2 digital sequence (Sobol' 1967) with Joe–Kuo direction numbers
    (`new-joe-kuo-6.21201`, the table SciPy uses). With 32-bit direction numbers
    $v_{j,1..32}$ for dimension $j$ and the Gray code $g(i) = i \oplus (i \gg 1)$,

    $$x_{ij} = 2^{-32} \bigoplus_{k:\ \text{bit } k \text{ of } g(i) \text{ set}} v_{j,k},$$

    computed directly (no sequential recurrence) with uint32 XORs, so point $i$ is
    the same whatever `n`, and `sobol(n, d, skip=s)` equals rows `s…s+n-1` of a longer
    call. Points lie in the open cube $(0, 1)^d$: a coordinate 0 (the whole first
    point, unscrambled) is returned as $2^{-p}$, $p$ the dtype's precision.
    Otherwise the unscrambled points equal
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

    **Returns:** an array of shape `(n, d)` in $(0,1)^d$.

    !!! Example

        ```python
        x = jaxmc.points.sobol(1024, 3, key=jax.random.key(0))
        ```
    """
    n = check_count(n, "n")
    d = check_count(d, "d")
    skip = check_skip(skip)
    if d > SOBOL_MAX_DIM:
        raise ValueError(f"`d` must be <= {SOBOL_MAX_DIM} for `sobol`, got {d}.")
    if n + skip > 2**32:
        raise ValueError(
            f"`skip + n` must be <= 2**32 (32-bit direction numbers), got skip={skip}, n={n}."
        )
    dtype = float_dtype(dtype)
    v = jnp.asarray(_sobol_directions()[:d])
    if key is None:
        return _sobol_plain(v, n, skip, dtype)
    return _sobol_scrambled(check_key(key), v, n, skip, dtype)

