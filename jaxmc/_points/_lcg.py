r"""The classic linear congruential generator, computed in parallel by an associative scan."""

from __future__ import annotations

import functools
import operator
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._checks import check_count
from ._common import below_one, float_dtype, x64_enabled


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
        work = jnp.uint64 if x64_enabled() else jnp.uint32  # m <= 2^16 without x64 (checked)
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
    acc = np.dtype(jnp.float64 if x64_enabled() else dtype)
    return jnp.minimum((x.astype(acc) / acc.type(m)).astype(dtype), below_one(dtype))


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
    if m & (m - 1) and not x64_enabled() and m > 2**16:
        raise ValueError(
            f"`m` = {m} is not a power of two; without jax_enable_x64 only m <= 2**16 "
            "is supported (the products need 64 bits)."
        )
    if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
        seed = _check_lcg_int(seed, "seed", 0, m)
        seed = np.uint64(seed) if x64_enabled() else np.uint32(seed)
    else:
        seed = jnp.asarray(seed)
        if seed.shape != () or not jnp.issubdtype(seed.dtype, jnp.integer):
            raise TypeError(
                f"`seed` must be an int or an integer scalar array, got {seed.dtype} {seed.shape}."
            )
    return _lcg(seed, n, a, c, m, float_dtype(dtype))

