r"""Halton points: van der Corput sequences in prime bases, optionally digit-permuted."""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._checks import check_count, check_key
from ._common import check_skip, float_dtype, open_unit, uint32_to_unit, x64_enabled


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
    exact_float = x64_enabled()
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
        unit = uint32_to_unit(words[2 * size :].reshape(d, width), jnp.dtype(acc))
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
    return open_unit(x.astype(dtype))


def halton(n: int, d: int, *, key: jax.Array | None = None, skip: int = 0, dtype=None) -> jax.Array:
    r"""Halton points `skip, …, skip + n - 1`, optionally randomised by digit permutations.

    Dimension $j$ is the van der Corput sequence in the $j$-th prime base $b_j$
    (2, 3, 5, …): if $i = \sum_t a_t b_j^t$, then $x_{ij} = \phi_{b_j}(i) =
    \sum_t a_t b_j^{-t-1}$ (Halton 1960; PBRT §7.4). Index 0 (the origin) comes
    first, as $2^{-p}$ (`p` the dtype's precision: points lie in the open cube
    $(0, 1)^d$); otherwise unscrambled points equal
    `scipy.stats.qmc.Halton(d, scramble=False)` after `fast_forward(skip)` (same
    order of floating-point operations).

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

    **Returns:** an array of shape `(n, d)` in $(0,1)^d$.
    """
    n = check_count(n, "n")
    d = check_count(d, "d")
    skip = check_skip(skip)
    limit = 2**50 if x64_enabled() else 2**31 - 1
    if n + skip > limit:
        raise ValueError(
            f"`skip + n` must be <= {limit} for `halton`"
            + ("" if x64_enabled() else " without jax_enable_x64")
            + f", got skip={skip}, n={n}."
        )
    dtype = float_dtype(dtype)
    return _halton(None if key is None else check_key(key), n, d, skip, dtype)

