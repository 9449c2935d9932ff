"""`jaxmc.points.lcg` with moduli that are not powers of two, without float64.

States are checked exactly against Python integers; float32 outputs against the
correctly rounded $x / m$, computed here from integers alone (going through a
Python float would round twice).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmc import points
from jaxmc._points._lcg import _Residues


MINSTD = dict(a=16807, c=0, m=2**31 - 1)
BELOW_ONE_F32 = np.nextafter(np.float32(1), np.float32(0))


def _states(seed, n, a, c, m):
    out, x = [], seed
    for _ in range(n):
        x = (a * x + c) % m
        out.append(x)
    return out


def _float32_quotient(x, m):
    """$x / m$ ($0 \\le x < m$) rounded to nearest-even float32, then clipped below 1."""
    if x == 0:
        return np.float32(0)
    e = 0  # find 2^23 <= x 2^e / m < 2^24: a 24-bit significand
    while x * 2**e < m * 2**23:
        e += 1
    while x * 2**e >= m * 2**24:
        e -= 1
    q, r = divmod(x * 2**e, m)
    if 2 * r > m or (2 * r == m and q % 2):
        q += 1
    return min(np.float32(q / 2**e), BELOW_ONE_F32)  # q / 2^e is exact in float64 and float32


def _float32_reference(seed, n, a, c, m):
    # The state 0 gives 2^-24, not 0: samples lie in the open interval (0, 1).
    return np.array([max(_float32_quotient(x, m), 2.0**-24) for x in _states(seed, n, a, c, m)],
                    np.float32)


def test_minstd_without_x64():
    # Park & Miller (CACM 1988): from x_0 = 1, x_10000 = 1043618065.
    assert _states(1, 10_000, **MINSTD)[-1] == 1043618065
    with jax.enable_x64(False):
        u = points.lcg(1, 10_000, **MINSTD)
    assert u.dtype == jnp.float32
    u = np.asarray(u)
    assert u[-1] == _float32_quotient(1043618065, 2**31 - 1)
    np.testing.assert_array_equal(u[:1000], _float32_reference(1, 1000, **MINSTD))
    # Under x64 the states are the same and float64 holds them exactly: x = round(u m).
    u64 = np.asarray(points.lcg(1, 10_000, **MINSTD, dtype=jnp.float64))
    assert round(float(u64[-1]) * (2**31 - 1)) == 1043618065
    np.testing.assert_array_equal(np.asarray(points.lcg(1, 10_000, **MINSTD, dtype=jnp.float32)), u)


@pytest.mark.parametrize("m", [3, 65537, 2**31 + 11, 3 * 2**30, 2**32 - 5])
def test_random_parameters_match_python(m):
    seed, a, c = (int(v) for v in np.random.default_rng(m).integers(0, m, 3))
    n = 500
    with jax.enable_x64(False):
        u32 = np.asarray(points.lcg(seed, n, a=a, c=c, m=m))
    np.testing.assert_array_equal(u32, _float32_reference(seed, n, a, c, m))
    u64 = np.asarray(points.lcg(seed, n, a=a, c=c, m=m, dtype=jnp.float64))
    np.testing.assert_array_equal(np.rint(u64 * m).astype(np.int64), _states(seed, n, a, c, m))


@pytest.mark.parametrize("x64", [False, True])
@pytest.mark.parametrize("m", [2**16 + 1, 2**31 - 1, 2**32 - 5])
def test_residue_arithmetic_at_the_extremes(m, x64):
    # Products and sums of the largest residues carry out of every 16- and 32-bit word.
    values = np.array([0, 1, 2, 2**16 - 1, 2**16, 2**31 - 1, m // 2, m - 2, m - 1], np.int64)
    values = np.unique(values[values < m])
    x, y = (v.ravel() for v in np.meshgrid(values, values))
    residues = _Residues(m)
    with jax.enable_x64(x64):  # uint32 words alone, or uint64 products
        xs, ys = jnp.asarray(x.astype(np.uint32)), jnp.asarray(y.astype(np.uint32))
        product = np.asarray(jax.jit(residues.mul)(xs, ys)).astype(np.int64)
        total = np.asarray(jax.jit(residues.add)(xs, ys)).astype(np.int64)
    np.testing.assert_array_equal(product, [int(p) * int(q) % m for p, q in zip(x, y)])
    np.testing.assert_array_equal(total, [(int(p) + int(q)) % m for p, q in zip(x, y)])


def test_float32_rounding_ties_and_values_next_to_one():
    # m = 3 * 2^25: x = 3 (2^24 + 1) gives x / m = (2^24 + 1) / 2^25, halfway between two
    # float32s (it rounds to even); the counter x -> x + 1 walks across it.
    m = 3 * 2**25
    seed = 3 * (2**24 + 1) - 4
    # x -> x - 1 from 0 walks down from m - 1, whose quotients round to 1 in float32.
    cases = [(seed, 1, 1, m), (0, 1, 2**32 - 6, 2**32 - 5)]
    with jax.enable_x64(False):
        for seed, a, c, m in cases:
            u = np.asarray(points.lcg(seed, 64, a=a, c=c, m=m))
            np.testing.assert_array_equal(u, _float32_reference(seed, 64, a, c, m))
    assert u[0] == BELOW_ONE_F32  # (m - 1) / m, clipped


def test_output_lies_in_the_unit_interval():
    # x -> x - 1 mod m from 0: the largest states first (float32 with m = 2^31 - 1 is
    # checked bit for bit above).
    with jax.enable_x64(False):
        for m, dtype in ((2**32, jnp.float32), (2**31 - 1, jnp.float16), (2**31 - 1, jnp.bfloat16)):
            u = points.lcg(0, 300, a=1, c=m - 1, m=m, dtype=dtype)
            assert u.dtype == dtype
            u = np.asarray(u.astype(jnp.float32))
            assert 0.0 <= u.min() and u.max() < 1.0, (m, dtype)


def test_traced_seed_under_jit_and_vmap():
    m, a, c = 2**32 - 5, 69069, 12345
    with jax.enable_x64(False):
        run = jax.jit(lambda s: points.lcg(s, 100, a=a, c=c, m=m))
        np.testing.assert_array_equal(run(jnp.uint32(4242)), _float32_reference(4242, 100, a, c, m))
        # A traced seed is taken modulo m, as Python's `%` does (also for negatives).
        np.testing.assert_array_equal(run(jnp.uint32(m + 3)), _float32_reference(3, 100, a, c, m))
        minstd = jax.vmap(lambda s: points.lcg(s, 20, **MINSTD))
        batch = minstd(jnp.array([-5, 1, 2], dtype=jnp.int32))
        for row, seed in zip(batch, (-5 % MINSTD["m"], 1, 2)):
            np.testing.assert_array_equal(row, _float32_reference(seed, 20, **MINSTD))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(m=2**32 + 1), "`m` must be in"),
        (dict(m=1), "`m` must be in"),
        (dict(a=2**31 - 1, m=2**31 - 1), "`a` must be in"),
        (dict(a=3, c=7, m=7), "`c` must be in"),
    ],
)
def test_parameters_are_checked(kwargs, match):
    with pytest.raises(ValueError, match=match):
        points.lcg(0, 4, **kwargs)
