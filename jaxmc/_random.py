r"""Counter-based random numbers in plain `jnp`: Threefry-2x32-20 and keyed permutations.

`jax.random` on the CPU computes Threefry through a kernel that XLA cannot fuse
or vectorise; written here as ordinary `uint32` array arithmetic, the same
generator (Salmon et al. 2011, "Parallel random numbers: as easy as 1, 2, 3",
the 20-round variant) fuses with its consumer and runs much faster on the CPU,
and just as well on accelerators. It is a pure function of a key and a counter,
so results are bit-identical under `jit`, `vmap` and any chunking.

A JAX key is first turned into a 64-bit Threefry key by one call to
`jax.random.bits`, so every key implementation works and the streams here are
unrelated to the ones `jax.random` draws from the same key.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax


__all__ = ["threefry2x32", "bits", "uniform", "permute"]

_U = np.uint32
_ROTATIONS = (13, 15, 26, 6, 17, 29, 16, 24)
_PARITY = _U(0x1BD11BDA)
# Feistel rounds of `permute`; each is one Threefry evaluation per element.
_FEISTEL_ROUNDS = 6


def _rotl(x: jax.Array, r: int) -> jax.Array:
    return (x << _U(r)) | (x >> _U(32 - r))


def threefry2x32(
    k0: jax.Array, k1: jax.Array, x0: jax.Array, x1: jax.Array
) -> tuple[jax.Array, jax.Array]:
    r"""The Threefry-2x32 block cipher with 20 rounds, on broadcastable `uint32` arrays.

    Key $(k_0, k_1)$, counter $(x_0, x_1)$. Each round is $x_0 \mathrel{+}= x_1;\;
    x_1 = \operatorname{rotl}(x_1, R_r) \oplus x_0$, and every fourth round injects
    the key schedule $k_2 = k_0 \oplus k_1 \oplus \texttt{0x1BD11BDA}$. Equal to
    `jax.extend.random.threefry_2x32` (tested against it and Random123's
    known-answer vectors).
    """
    ks = (k0, k1, k0 ^ k1 ^ _PARITY)
    x0 = x0 + ks[0]
    x1 = x1 + ks[1]
    for r in range(20):
        x0 = x0 + x1
        x1 = _rotl(x1, _ROTATIONS[r % 8]) ^ x0
        if r % 4 == 3:
            s = r // 4 + 1
            x0 = x0 + ks[s % 3]
            x1 = x1 + ks[(s + 1) % 3] + _U(s)
    return x0, x1


def _cipher_key(key: jax.Array) -> tuple[jax.Array, jax.Array]:
    words = jax.random.bits(key, (2,), jnp.uint32)
    return words[0], words[1]


def _counter_words(key: jax.Array, shape: tuple[int, ...]) -> tuple[jax.Array, jax.Array]:
    """The two Threefry output words at counter `(flat index, 0)` for every entry of `shape`.

    One cipher block per entry, even when only one word is used: the alternative
    (splitting the two words of a block over two entries) needs a concatenation
    that stops XLA from vectorising the loop it is fused into.
    """
    if math.prod(shape) > 2**32:
        raise ValueError(f"At most 2**32 random entries per key, asked for shape {shape}.")
    k0, k1 = _cipher_key(key)
    c = lax.iota(jnp.uint32, math.prod(shape)).reshape(shape)
    return threefry2x32(k0, k1, c, jnp.zeros_like(c))


def bits(key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """Uniform random `uint32` words of `shape`."""
    return _counter_words(key, shape)[0]


def uniform(key: jax.Array, shape: tuple[int, ...], dtype) -> jax.Array:
    r"""Uniform floats in the open interval $(0, 1)$ of `shape` and floating `dtype`.

    Each value is the midpoint of one of $2^k$ equal cells, $(j + \tfrac12)\,2^{-k}$
    with $j$ uniform, so it is never 0 or 1, $1 - u$ has the same law, and the
    mean is exactly $\tfrac12$. Single and lower precision, $k = 23$: the top
    23 bits of a word fill the mantissa of a float in $[1, 2)$ and
    $1 - 2^{-24}$ is subtracted (exactly, by Sterbenz's lemma), so
    $u \in [2^{-24}, 1 - 2^{-24}]$. Double precision, $k = 52$: 26 bits from
    each word of one Threefry block, $(\lfloor a/2^6 \rfloor 2^{26} + \lfloor
    b/2^6 \rfloor + \tfrac12)\, 2^{-52}$, exact in float64. Lower precisions round
    the float32 value, kept within $[\text{tiny}, 1)$.
    """
    dtype = jnp.dtype(dtype)
    if jnp.finfo(dtype).nmant > 23:
        a, b = _counter_words(key, shape)
        hi = (a >> _U(6)).astype(dtype) * dtype.type(2.0**26)
        return (hi + (b >> _U(6)).astype(dtype) + dtype.type(0.5)) * dtype.type(2.0**-52)
    words = bits(key, shape)
    one_to_two = lax.bitcast_convert_type((words >> _U(9)) | _U(0x3F800000), jnp.float32)
    u = one_to_two - np.float32(1.0 - 2.0**-24)
    if dtype == jnp.float32:
        return u
    below_one = np.nextafter(np.array(1.0, dtype), np.array(0.0, dtype))
    return jnp.clip(u.astype(dtype), jnp.finfo(dtype).tiny, below_one)


def categorical(key: jax.Array, log_weights: jax.Array, n: int) -> jax.Array:
    r"""`n` i.i.d. indices into `log_weights` `(K,)`, index $k$ with probability
    $\mathrm{softmax}(\text{log\_weights})_k$, by inverting the CDF at one uniform each
    (`jax.random.categorical`'s Gumbel trick draws and takes two logs of $K$ per index).
    """
    cdf = jnp.cumsum(jax.nn.softmax(lax.stop_gradient(log_weights)))
    u = uniform(key, (n,), cdf.dtype) * cdf[-1]
    k = jnp.searchsorted(cdf, u, side="right", method="compare_all")
    return jnp.minimum(k, log_weights.shape[0] - 1).astype(jnp.int32)


def _uniform_below(k0: jax.Array, k1: jax.Array, stream: jax.Array, n: int) -> jax.Array:
    """One exactly uniform integer in $[0, n)$ per entry of `stream` (rejection sampling)."""
    if n & (n - 1) == 0:
        return threefry2x32(k0, k1, stream, jnp.zeros_like(stream))[0] & _U(n - 1)
    # Words at or above the largest multiple of n below 2^32 are redrawn (p < 1/2 each).
    limit = _U((2**32 // n) * n)
    draw = lambda attempt: threefry2x32(k0, k1, stream, attempt)[0]
    rejected = lambda state: jnp.any(state[1] >= limit)

    def redraw(state):
        attempt, word = state
        again = word >= limit
        attempt = jnp.where(again, attempt + _U(1), attempt)
        return attempt, jnp.where(again, draw(attempt), word)

    attempt = jnp.zeros_like(stream)
    _, word = lax.while_loop(rejected, redraw, (attempt, draw(attempt)))
    return word % _U(n)


def permute(key: jax.Array, index: jax.Array, n: int, stream: jax.Array | int = 0) -> jax.Array:
    r"""$\pi(i)$ for a keyed pseudorandom permutation $\pi$ of $\{0, \dots, n-1\}$.

    $\pi(i) = (\phi(i) + s) \bmod n$. Here $\phi$ is a Feistel network on
    $k = \lceil \log_2 n \rceil$ bits (halves of $\lfloor k/2 \rfloor$ and
    $\lceil k/2 \rceil$ bits, alternating): each round maps $(L, R) \mapsto (R,\,
    L \oplus F_r(R))$ with $F_r$ Threefry at counter $(R, \text{rounds} \cdot
    \text{stream} + r)$, a bijection of $[0, 2^k)$ whatever $F_r$ is. Values that
    land in $[n, 2^k)$ are mapped again (cycle walking, Black & Rogaway 2002) until
    they fall below $n$, which keeps $\phi$ a bijection of $[0, n)$; since
    $2^k < 2n$, fewer than two passes are needed on average. This is how PBRT-v4
    permutes samples (`PermutationElement`), with a stronger round function, and
    it needs no sort: $O(n)$ work, fully parallel.

    The rotation by an exactly uniform $s \in [0, n)$ makes every $\pi(i)$ exactly
    uniform on $[0, n)$ whatever $\phi$ is. What a Feistel network cannot give is
    a uniform draw from all $n!$ permutations: for small $n$ it reaches only a
    subset (balanced Feistel maps are even permutations), so callers that need
    the full symmetric group at small $n$ should sort random keys instead.

    `index` is a `uint32` array of values below `n`; `stream` (a `uint32` scalar or
    array broadcastable with `index`) selects one of many independent permutations
    for the same key.
    """
    if n <= 1:
        return jnp.zeros_like(index)
    key_rounds, key_shift = jax.random.split(key)
    k0, k1 = _cipher_key(key_rounds)
    width = (n - 1).bit_length()
    stream = jnp.asarray(stream, jnp.uint32)
    counter = stream * _U(_FEISTEL_ROUNDS)

    def feistel(x):
        for r in range(_FEISTEL_ROUNDS):
            low_bits = width - width // 2 if r % 2 == 0 else width // 2
            high_bits = width - low_bits
            low = x & _U((1 << low_bits) - 1)
            high = x >> _U(low_bits)
            f, _ = threefry2x32(k0, k1, low, counter + _U(r))
            x = (low << _U(high_bits)) | (high ^ (f & _U((1 << high_bits) - 1)))
        return x

    x = feistel(index.astype(jnp.uint32))
    if n != 1 << width:
        outside = lambda x: jnp.any(x >= _U(n))
        x = lax.while_loop(outside, lambda x: jnp.where(x >= _U(n), feistel(x), x), x)
    shift = _uniform_below(*_cipher_key(key_shift), stream, n)
    return (x + shift) % _U(n)
