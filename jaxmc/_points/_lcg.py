r"""The classic linear congruential generator, computed in parallel by jumping ahead.

The arithmetic is exact for every modulus $m \le 2^{32}$ in uint32 alone, so it
needs no `jax_enable_x64` (with it, 64-bit products are faster); the states do not
depend on that switch.
"""

from __future__ import annotations

import functools
import math
import operator
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._checks import check_count
from ._common import float_dtype, open_unit, x64_enabled


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


class _Residues:
    r"""Exact $(x + y) \bmod m$ and $x y \bmod m$ for residues $x, y < m$ held in uint32.

    Moduli that divide $2^{32}$ use uint32 wrap-around, and moduli $m \le 2^{16}$
    a plain `%` ($x y < 2^{32}$ fits), as does any modulus under `jax_enable_x64`
    ($x y < 2^{64}$). Otherwise the product is formed exactly as
    a 64-bit number from four 16-bit partial products, $x y = h \cdot 2^{32} + l$
    with $h < m$ (because $x, y < m$), and reduced by Horner's rule over the four
    bytes $b_3 b_2 b_1 b_0$ of $l$: $r \leftarrow (2^8 r + b_k) \bmod m$, starting
    from $r = h$. With $r < m < 2^{32}$,

    $$2^8 r + b = \lfloor r / 2^{24} \rfloor \, 2^{32} + \big((2^8 r + b) \bmod 2^{32}\big)
      \equiv T[\lfloor r / 2^{24} \rfloor] + \big((2^8 r + b) \bmod 2^{32}\big) \pmod m,$$

    where $T[j] = j \, 2^{32} \bmod m$ ($j < 2^8$) is a table computed once in
    Python; both terms are residues after one uint32 `%`, and `add` sums them.
    `add` detects the carry out of 32 bits (possible when $m > 2^{31}$): then,
    as when $x + y \ge m$, the wrapped $x + y - m$ is exact.
    """

    def __init__(self, m: int):
        self.wraps = m & (m - 1) == 0
        self.mask = np.uint32(m - 1) if self.wraps and m < 2**32 else None
        self.m = np.uint32(m) if m < 2**32 else None  # unused for 2^32: uint32 wraps
        self.small = m <= 2**16
        if not (self.wraps or self.small):
            self.table = np.array([(j << 32) % m for j in range(256)], dtype=np.uint32)

    def _wrap(self, x: jax.Array) -> jax.Array:
        return x if self.mask is None else x & self.mask

    def add(self, x: jax.Array, y: jax.Array) -> jax.Array:
        s = x + y
        if self.wraps:
            return self._wrap(s)
        return jnp.where((s < x) | (s >= self.m), s - self.m, s)

    def mul(self, x: jax.Array, y: jax.Array) -> jax.Array:
        if self.wraps:
            return self._wrap(x * y)
        if self.small:
            return (x * y) % self.m
        if x64_enabled():  # the same residues, faster
            wide = jnp.asarray(x).astype(jnp.uint64) * jnp.asarray(y).astype(jnp.uint64)
            return (wide % np.uint64(self.m)).astype(jnp.uint32)
        hi, lo = _multiply_wide(x, y)
        table = jnp.asarray(self.table)
        r = hi
        for shift in (24, 16, 8, 0):
            byte = (lo >> np.uint32(shift)) & np.uint32(0xFF)
            low = ((r << np.uint32(8)) | byte) % self.m
            r = self.add(table.at[r >> np.uint32(24)].get(mode="promise_in_bounds"), low)
        return r


def _multiply_wide(x: jax.Array, y: jax.Array) -> tuple[jax.Array, jax.Array]:
    r"""The exact product of two uint32 arrays as $(h, l)$, $x y = h \cdot 2^{32} + l$."""
    sixteen, mask = np.uint32(16), np.uint32(0xFFFF)
    x0, x1 = x & mask, x >> sixteen
    y0, y1 = y & mask, y >> sixteen
    low, high, cross = x0 * y0, x1 * y1, x0 * y1
    middle = cross + x1 * y0  # may carry out of 32 bits: the carry is worth 2^48
    middle_carry = (middle < cross).astype(jnp.uint32)
    lo = low + (middle << sixteen)
    lo_carry = (lo < low).astype(jnp.uint32)
    hi = high + (middle >> sixteen) + (middle_carry << sixteen) + lo_carry
    return hi, lo


def _quotient_to_float(x: jax.Array, m: int) -> jax.Array:
    r"""$x / m$ correctly rounded to float32, for uint32 $x < m < 2^{32}$, in integer arithmetic.

    Shift $x$ left by $s$ so that its leading bit lines up with that of $m$, so
    $x 2^s / m \in (1/2, 2)$; then 26 steps of binary long division give
    $q = \lfloor x 2^{s + 26} / m \rfloor \in [2^{25}, 2^{27})$ and the remainder.
    Setting the last bit of $q$ when the remainder is non-zero (a sticky bit,
    below at least two bits that float32's 24-bit significand drops) makes the
    round-to-nearest conversion of $q$ round $x 2^{s + 26} / m$ itself; the
    scaling by $2^{-(s + 26)} \ge 2^{-57}$ is exact. $x = 0$ gives 0.
    """
    steps = 26
    modulus = np.uint32(m)
    one = np.uint32(1)
    shift = lax.clz(x) - np.uint32(32 - m.bit_length())  # clz(x) >= clz(m) as x < m
    r = x << shift
    q = (r >= modulus).astype(jnp.uint32)
    r = jnp.where(q == one, r - modulus, r)
    for _ in range(steps):
        # 2r may carry out of 32 bits when m > 2^31; 2r - m < m is then the wrapped value.
        doubled = r << one
        bit = ((r >> np.uint32(31)) == one) | (doubled >= modulus)
        r = jnp.where(bit, doubled - modulus, doubled)
        q = (q << one) | bit.astype(jnp.uint32)
    q = q | (r != 0).astype(jnp.uint32)
    # 2^-(s + 26) built from its exponent bits: 127 is float32's exponent bias.
    scale = lax.bitcast_convert_type((np.uint32(127 - steps) - shift) << np.uint32(23), jnp.float32)
    return q.astype(jnp.float32) * scale


def _affine_powers(a: int, c: int, m: int, count: int) -> tuple[np.ndarray, np.ndarray]:
    r"""$(A_t, C_t)$ with $f^t(x) = A_t x + C_t \bmod m$, $f(x) = a x + c$, for $t < $ `count`."""
    big_a, big_c = np.empty(count, np.uint32), np.empty(count, np.uint32)
    power_a, power_c = 1, 0
    for t in range(count):
        big_a[t], big_c[t] = power_a, power_c
        power_a, power_c = a * power_a % m, (a * power_c + c) % m
    return big_a, big_c


def _to_unit(x: jax.Array, m: int, dtype: np.dtype) -> jax.Array:
    """States $x < m$ as $x / m$ in `dtype`, below 1."""
    if jnp.finfo(dtype).nmant >= 32:  # float64: x and m are exact, one rounding
        u = x.astype(dtype) / dtype.type(m)
    elif m & (m - 1) == 0:  # one rounding of x, exact scaling
        u = (x.astype(jnp.float32) * np.float32(1.0 / m)).astype(dtype)
    else:
        u = _quotient_to_float(x, m).astype(dtype)
    # (m - 1) / m rounds to 1 when m exceeds 2^(significand bits).
    return open_unit(u)  # x = 0 (and x/m rounded to 1) stay inside (0, 1)


@functools.partial(jax.jit, static_argnames=("n", "a", "c", "m", "dtype"))
def _lcg(seed, n, a, c, m, dtype):
    # x_{jB + t} = f^t(x_{jB}) with blocks of B ~ sqrt(n): the tables of f^t (t <= B)
    # and of f^{jB} depend only on the static a, c, m, n, so Python computes them
    # once and the device does one multiply-add per state (and one per block).
    block = math.isqrt(n - 1) + 1
    blocks = -(-n // block)
    step_a, step_c = _affine_powers(a, c, m, block + 1)
    jump_a, jump_c = _affine_powers(int(step_a[-1]), int(step_c[-1]), m, blocks)
    step_a, step_c, jump_a, jump_c = map(jnp.asarray, (step_a[1:], step_c[1:], jump_a, jump_c))
    residues = _Residues(m)
    starts = residues.add(residues.mul(jump_a, _seed_residue(seed, m)), jump_c)

    def one_block(start):
        return _to_unit(residues.add(residues.mul(step_a, start), step_c), m, dtype)

    # A loop over blocks, not one (blocks, B) broadcast: XLA's CPU code for the
    # long integer chains is much slower on the 2-D broadcast.
    return lax.map(one_block, starts).reshape(-1)[:n]


def _seed_residue(seed: jax.Array, m: int) -> jax.Array:
    """An integer scalar reduced to $[0, m)$ as uint32 (Python's `seed % m`)."""
    if m == 2**32:
        return seed.astype(jnp.uint32)
    modulus = np.uint32(m)
    if jnp.issubdtype(seed.dtype, jnp.unsignedinteger):
        if seed.dtype.itemsize > 4:
            seed = seed % seed.dtype.type(m)
        return seed.astype(jnp.uint32) % modulus
    if seed.dtype.itemsize > 4:
        return (seed % seed.dtype.type(m)).astype(jnp.uint32)  # `%` takes the sign of m
    magnitude = (jnp.abs(seed.astype(jnp.int32)).astype(jnp.uint32)) % modulus
    return jnp.where((seed < 0) & (magnitude > 0), modulus - magnitude, magnitude)


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

    The defaults are the *Numerical Recipes* constants (Knuth, TAOCP vol. 2 §3.2);
    `a=16807, c=0, m=2**31 - 1` is Park and Miller's MINSTD.
    The $n$ states are computed in parallel by jumping ahead: with $f(x) = a x + c$,
    $f^t(x) = A_t x + C_t \pmod m$. For blocks of $B \approx \sqrt n$ states,
    the coefficients of $f^t$ ($t \le B$) and of $f^{jB}$ depend only on
    $a, c, m, n$ and are computed once when tracing; the device then computes the
    block starts $x_{jB} = f^{jB}(x_0)$ and every $x_{jB + t} = f^t(x_{jB})$.

    Every modulus $m \le 2^{32}$ is exact in 32-bit integers, with or without
    `jax_enable_x64`: moduli that divide $2^{32}$ use uint32 wrap-around, others
    form each 64-bit product from 16-bit halves and reduce it modulo $m$ a byte
    at a time (or, under x64, in uint64: the same states, faster). In float32, $x_i / m$ is correctly rounded (computed by integer
    long division, not through a rounded $m$; float16 and bfloat16 round that
    once more); in float64 it is one division.
    This is a teaching generator — its low bits and lattice structure are poor;
    use `jax.random` for real work.

    **Arguments:**

    - `seed`: the state $x_0$, an int in $[0, m)$, or a (possibly traced) integer
      scalar array, taken modulo $m$.
    - `n`: number of outputs (static int `>= 1`).
    - `a`, `c`, `m`: multiplier, increment and modulus (static ints, $0 \le a, c < m$,
      $2 \le m \le 2^{32}$).
    - `dtype`: floating dtype of the result. Values lie in the open interval:
      the state 0 gives $2^{-p}$, and values that round to 1 (when $m$ exceeds
      $2^{24}$ in float32) give the largest float below 1, $1 - 2^{-p}$.

    **Returns:** an array of shape `(n,)` in $(0, 1)$.

    !!! Example

        ```python
        u = jaxmc.points.lcg(1, 10_000, a=16807, c=0, m=2**31 - 1)
        # u[-1] is 1043618065 / (2**31 - 1): Park and Miller's check of state 10000.
        ```
    """
    n = check_count(n, "n")
    m = _check_lcg_int(m, "m", 2, 2**32 + 1)
    a = _check_lcg_int(a, "a", 0, m)
    c = _check_lcg_int(c, "c", 0, m)
    if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
        seed = np.uint32(_check_lcg_int(seed, "seed", 0, m))
    else:
        seed = jnp.asarray(seed)
        if seed.shape != () or not jnp.issubdtype(seed.dtype, jnp.integer):
            raise TypeError(
                f"`seed` must be an int or an integer scalar array, got {seed.dtype} {seed.shape}."
            )
    return _lcg(seed, n, a, c, m, float_dtype(dtype))
