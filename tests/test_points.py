"""Tests of `jaxmc.points`: exactness against SciPy, structure, and uniformity.

Statistical checks use fixed keys and a Bonferroni-corrected p-value floor of
1e-4 over all the tests in a check.
"""

import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats
from scipy.stats import qmc

from jaxmc import points

from .helpers import P_FLOOR, assert_uniform, one_per_bin


def _scipy_engine(engine, skip):
    if skip:
        engine.fast_forward(skip)
    return engine


_PRIMES = (2, 3, 5, 7, 11, 13, 17, 19, 23, 29, 31, 37)


def _halton_reference(n, d, skip):
    """Unscrambled Halton points `skip .. skip + n - 1` by exact radical inverses (SciPy's
    `fast_forward` walks the skipped points one by one: 15 s to 2^24)."""
    index = np.arange(skip, skip + n, dtype=np.int64)
    out = np.zeros((n, d))
    for j, base in enumerate(_PRIMES[:d]):
        rest, scale = index.copy(), 1.0 / base
        while np.any(rest):
            out[:, j] += (rest % base) * scale
            rest, scale = rest // base, scale / base
    return out


def test_halton_reference_matches_scipy():
    np.testing.assert_allclose(_halton_reference(600, 12, 1000),
                               _scipy_engine(qmc.Halton(12, scramble=False), 1000).random(600),
                               rtol=0, atol=1e-15)


# -------------------------------------------------------------------- exactness


@pytest.mark.parametrize(
    "n, d, skip",
    [
        (1, 1, 0),
        (64, 2, 0),
        (1000, 10, 0),
        (1000, 10, 37),
        (333, 40, 1024),
        (8, 1000, 0),
        (5, 1000, 3),
    ],
)
def test_sobol_equals_scipy(n, d, skip):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # SciPy warns about n not a power of two
        expected = _scipy_engine(qmc.Sobol(d, scramble=False), skip).random(n)
    actual = np.asarray(points.sobol(n, d, skip=skip))
    assert actual.dtype == np.float64
    # Points lie in the open cube: SciPy's coordinate 0 (point 0) is 2**-53 here.
    np.testing.assert_array_equal(actual, np.maximum(expected, 2**-53))


def test_sobol_max_dim_and_float32():
    expected = qmc.Sobol(points.SOBOL_MAX_DIM, scramble=False).random(4)
    np.testing.assert_array_equal(
        np.asarray(points.sobol(4, points.SOBOL_MAX_DIM)), np.maximum(expected, 2**-53)
    )
    # float32 keeps the top 24 bits: truncation, never rounding up to 1; never 0 either.
    x32 = np.asarray(points.sobol(256, 3, skip=5, dtype=jnp.float32))
    ref = qmc.Sobol(3, scramble=False)
    ref.fast_forward(5)
    np.testing.assert_array_equal(x32, np.maximum(np.floor(ref.random(256) * 2**24), 1) / 2**24)


@pytest.mark.parametrize("skip", [0, 2**24 - 300, 2**24 + 5])
def test_halton_without_x64_matches_scipy(skip):
    # Without x64, digits come from int32 indices: by a float32 multiply with an
    # integer correction below 2^24, by integer division above. Sums are float32.
    with jax.enable_x64(False):
        plain = np.asarray(points.halton(600, 12, skip=skip))
        permuted = np.asarray(points.halton(600, 12, skip=skip, key=jax.random.key(3)))
    assert plain.dtype == np.float32
    expected = _halton_reference(600, 12, skip)
    np.testing.assert_allclose(plain, expected, rtol=0, atol=4e-7)
    # Randomised, dimension 0 (base 2) keeps one point in each half per aligned pair.
    start = skip % 2
    halves = np.floor(permuted[start : start + 598, 0] * 2).reshape(-1, 2)
    np.testing.assert_array_equal(halves.sum(axis=1), 1.0)
    assert permuted.min() >= 0.0 and permuted.max() < 1.0
    assert np.abs(permuted - plain).max() > 0.1


@pytest.mark.parametrize("n, d, skip", [(1, 1, 0), (100, 5, 0), (1000, 10, 37), (500, 60, 11)])
def test_halton_equals_scipy(n, d, skip):
    expected = _scipy_engine(qmc.Halton(d, scramble=False), skip).random(n)
    # Points lie in the open cube: SciPy's origin (index 0) is 2**-53 here.
    np.testing.assert_array_equal(
        np.asarray(points.halton(n, d, skip=skip)), np.maximum(expected, 2**-53)
    )


def test_skip_is_a_slice_of_a_longer_sequence(key):
    for fn in (points.sobol, points.halton):
        full = fn(1064, 5, key=key)
        np.testing.assert_array_equal(fn(64, 5, key=key, skip=1000), full[1000:])
        np.testing.assert_array_equal(fn(300, 4), jnp.concatenate([fn(7, 4), fn(293, 4, skip=7)]))


def test_lattice_formula():
    n, d = 1024, 6
    z = np.array([1, 182667, 469891, 498753, 110745, 446247])
    expected = np.maximum((np.arange(n)[:, None] * z[None, :] % n) / n, 2**-53)  # open cube
    np.testing.assert_array_equal(np.asarray(points.lattice(n, d)), expected)
    # Not a power of two: exact int64 indices; XLA may divide by n with a rounded reciprocal.
    odd = np.asarray(points.lattice(1000, 3))
    np.testing.assert_allclose(
        odd, np.maximum((np.arange(1000)[:, None] * z[None, :3] % 1000) / 1000, 2**-53), rtol=3e-16
    )


# -------------------------------------------------------------------- structure


@pytest.mark.parametrize("scrambled", [False, True])
def test_sobol_balance(key, scrambled):
    # The first 2^m points form a (t, m, d)-net: every 1-D projection has one point in each
    # dyadic interval of length 2^-m, and LMS + digital shift keeps that.
    k = key if scrambled else None
    for m in (1, 4, 9):
        assert one_per_bin(points.sobol(2**m, 64, key=k), 2**m), m
    # ... also for the block [2^m, 2^(m+1)) of the sequence.
    assert one_per_bin(points.sobol(2**8, 16, key=k, skip=2**8), 2**8)


def test_sobol_scrambled_two_dimensional_net(key):
    # Dimensions 0 and 1 of Sobol' have t = 0: each of the 2^m elementary boxes of shape
    # 2^-a x 2^-(m-a) holds exactly one of the first 2^m points.
    m = 8
    x = np.asarray(points.sobol(2**m, 2, key=key))
    for a in range(m + 1):
        cells = np.floor(x[:, 0] * 2**a).astype(int) * 2 ** (m - a) + np.floor(
            x[:, 1] * 2 ** (m - a)
        ).astype(int)
        assert np.array_equal(np.sort(cells), np.arange(2**m)), a


def test_halton_scrambled_keeps_strata(key):
    # Digit permutations keep the van der Corput strata: the first b^m points of the
    # base-b dimension have one point in each interval of length b^-m.
    x = np.asarray(points.halton(3**5, 3, key=key))
    assert one_per_bin(x[:, 1:2], 3**5)
    assert one_per_bin(x[:128, 0:1], 128)
    x = np.asarray(points.halton(5**3, 3, key=key))
    assert one_per_bin(x[:, 2:3], 5**3)


def test_stratified_one_point_per_cell(key):
    counts = (4, 3, 5)
    x = np.asarray(points.stratified(key, counts))
    assert x.shape == (60, 3)
    cells = np.floor(x * np.array(counts)).astype(int)
    expected = np.stack(np.meshgrid(*[np.arange(c) for c in counts], indexing="ij"), -1)
    np.testing.assert_array_equal(cells, expected.reshape(-1, 3))
    assert points.stratified(key, (7,)).shape == (7, 1)


@pytest.mark.parametrize("n, d", [(1, 1), (10, 3), (1000, 8), (4097, 2)])
def test_latin_hypercube_one_point_per_bin(key, n, d):
    x = points.latin_hypercube(key, n, d)
    assert x.shape == (n, d)
    assert one_per_bin(x, n)


def test_latin_hypercube_permutations_are_uniform():
    # n = 3: the bins of point 0 and 1 on axis 0 determine the permutation; chi^2 over 6.
    keys = jax.random.split(jax.random.key(11), 6000)
    x = jax.vmap(lambda k: points.latin_hypercube(k, 3, 1))(keys)
    bins = np.floor(np.asarray(x[:, :, 0]) * 3).astype(int)
    codes = bins[:, 0] * 3 + bins[:, 1]
    counts = np.array([np.sum(codes == c) for c in (1, 2, 3, 5, 6, 7)])
    assert counts.sum() == 6000
    assert stats.chisquare(counts).pvalue > P_FLOOR, counts


# -------------------------------------------------------------------- randomisation


RANDOMISED = {
    "sobol": lambda k: points.sobol(64, 5, key=k),
    "sobol_skip": lambda k: points.sobol(64, 5, key=k, skip=1000),
    "halton": lambda k: points.halton(64, 5, key=k),
    "halton_skip": lambda k: points.halton(64, 5, key=k, skip=777),
    "lattice": lambda k: points.lattice(64, 5, key=k),
    "latin_hypercube": lambda k: points.latin_hypercube(k, 64, 5),
    # Each jittered point is uniform in its own cell: rescale the cell to [0,1)^d.
    "stratified": lambda k: jnp.mod(
        points.stratified(k, (8, 8, 1, 1, 1)) * jnp.array([8, 8, 1, 1, 1]), 1.0
    ),
    "uniform": lambda k: points.uniform(k, 64, 5),
}


@pytest.mark.parametrize("name", sorted(RANDOMISED))
def test_randomised_points_are_marginally_uniform(name):
    # Each fixed point index, over independent keys, is uniform on [0,1)^d: KS of rows 0, 1
    # and 37 in every dimension over 2000 keys (Bonferroni over the 15 tests).
    fn = RANDOMISED[name]
    keys = jax.random.split(jax.random.key(1234), 2000)
    x = np.asarray(jax.jit(jax.vmap(fn))(keys))
    assert x.min() >= 0.0 and x.max() < 1.0
    assert_uniform(x[:, [0, 1, 37], :], name)
    # jit + vmap over keys gives what one call per key gives (up to the last bit: XLA may
    # fuse a product into an FMA differently in the batched program).
    for i in (0, 1999):
        np.testing.assert_allclose(x[i], np.asarray(fn(keys[i])), rtol=1e-15, atol=0)


@pytest.mark.parametrize("name", sorted(RANDOMISED))
def test_keys_determine_points(name, key):
    fn = RANDOMISED[name]
    k1, k2 = jax.random.split(key)
    a, b, c = fn(k1), fn(k1), fn(k2)
    np.testing.assert_array_equal(a, b)
    assert not np.any(np.all(np.asarray(a) == np.asarray(c), axis=1))


def test_legacy_keys(key):
    legacy = points.sobol(64, 5, key=jax.random.PRNGKey(3))
    assert legacy.shape == (64, 5) and float(legacy.max()) < 1.0


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_scrambled_sobol_points_sit_at_the_centres_of_their_cells(key, dtype):
    # A random digital shift makes each 32-bit word uniform: a point at its cell's left end
    # would average f over the cells' left ends, biased by 2^-33 per axis. At the centres,
    # word x and its mirror 2^32 - 1 - x land symmetrically about 1/2, so E[u] = 1/2.
    from jaxmc._points._common import uint32_to_unit

    words = jax.random.bits(key, (4096,), jnp.uint32)
    u = uint32_to_unit(words, jnp.dtype(dtype), centred=True)
    mirrored = uint32_to_unit(~words, jnp.dtype(dtype), centred=True)
    np.testing.assert_array_equal(np.asarray(u, np.float64) + np.asarray(mirrored, np.float64), 1.0)
    assert float(u.min()) > 0.0 and float(u.max()) < 1.0
    x = np.asarray(points.sobol(2**10, 3, key=key, dtype=dtype), np.float64)
    cells = 2.0**-32 if dtype == jnp.float64 else 2.0**-23
    np.testing.assert_array_equal(np.mod(x, cells), cells / 2)


def test_large_scrambled_sets_are_uniform(key):
    # Within one randomised set the empirical distribution is (much better than) uniform.
    for x in (points.sobol(4096, 8, key=key), points.halton(4096, 8, key=key)):
        assert_uniform(x, "large set")


def test_float32_results_stay_below_one(key):
    for x in (
        points.sobol(4096, 3, key=key, dtype=jnp.float32),
        points.halton(4096, 3, key=key, dtype=jnp.float32),
        points.lattice(4096, 3, key=key, dtype=jnp.float32),
        points.latin_hypercube(key, 4096, 3, dtype=jnp.float32),
    ):
        assert x.dtype == jnp.float32
        assert float(x.min()) >= 0.0 and float(x.max()) < 1.0


# -------------------------------------------------------------------- lcg and shuffle


def _lcg_reference(seed, n, a, c, m):
    out, x = [], seed
    for _ in range(n):
        x = (a * x + c) % m
        out.append(max(x / m, 2**-53))  # the open interval: the state 0 gives 2**-53
    return np.array(out)


@pytest.mark.parametrize(
    "seed, a, c, m",
    [
        (0, 1664525, 1013904223, 2**32),
        (12345, 1664525, 1013904223, 2**32),
        (7, 1103515245, 12345, 2**31),
        (42, 16807, 0, 2**31 - 1),  # MINSTD, a prime modulus
        (3, 5, 3, 16),
        (1, 2, 1, 11),
    ],
)
def test_lcg_matches_python(seed, a, c, m):
    n = 1000
    expected = _lcg_reference(seed, n, a, c, m)
    actual = np.asarray(points.lcg(seed, n, a=a, c=c, m=m))
    # The states are exact; x/m is exact for powers of two, and within an ulp otherwise
    # (XLA may divide by a constant through its rounded reciprocal).
    np.testing.assert_allclose(actual, expected, rtol=0 if m & (m - 1) == 0 else 2.3e-16, atol=0)


def test_lcg_traced_seed():
    expected = _lcg_reference(12345, 100, 1664525, 1013904223, 2**32)
    np.testing.assert_array_equal(
        np.asarray(jax.jit(lambda s: points.lcg(s, 100))(jnp.uint32(12345))), expected
    )


def test_shuffle_is_a_permutation(key):
    x = jnp.arange(1000 * 2).reshape(1000, 2)
    y = np.asarray(points.shuffle(key, x))
    assert y.shape == x.shape
    np.testing.assert_array_equal(np.sort(y[:, 0]), np.arange(0, 2000, 2))
    np.testing.assert_array_equal(y[:, 1], y[:, 0] + 1)  # rows move together
    assert not np.array_equal(y, np.asarray(x))
    np.testing.assert_array_equal(points.shuffle(key, jnp.ones((1, 3))), jnp.ones((1, 3)))


def test_shuffle_is_uniform_over_permutations():
    keys = jax.random.split(jax.random.key(5), 6000)
    y = np.asarray(jax.jit(jax.vmap(lambda k: points.shuffle(k, jnp.arange(3))))(keys))
    codes = y[:, 0] * 9 + y[:, 1] * 3 + y[:, 2]
    outcomes = [
        0 * 9 + 1 * 3 + 2,
        0 * 9 + 2 * 3 + 1,
        1 * 9 + 0 * 3 + 2,
        1 * 9 + 2 * 3 + 0,
        2 * 9 + 0 * 3 + 1,
        2 * 9 + 1 * 3 + 0,
    ]
    counts = np.array([np.sum(codes == c) for c in outcomes])
    assert counts.sum() == 6000, counts
    assert stats.chisquare(counts).pvalue > P_FLOOR, counts


# -------------------------------------------------------------------- discrepancy


@pytest.mark.parametrize("method", ["CD", "L2-star"])
def test_discrepancy_equals_scipy(method, key):
    for x in (
        np.asarray(points.uniform(key, 200, 3)),
        np.asarray(points.sobol(128, 5)),
        np.asarray(points.halton(50, 1)),
    ):
        expected = qmc.discrepancy(x, method=method)
        # Cancellation of O(1) terms: agreement to float64 round-off of those terms.
        actual = float(points.discrepancy(x, method=method))
        np.testing.assert_allclose(actual, expected, rtol=1e-9, atol=1e-12)
    # Low-discrepancy sets beat i.i.d. points.
    iid = points.discrepancy(points.uniform(key, 512, 4), method=method)
    assert points.discrepancy(points.sobol(512, 4), method=method) < iid


def test_discrepancy_chunked_matches_unchunked(key):
    x = points.uniform(key, 3000, 2)  # large enough to need several row blocks
    expected = qmc.discrepancy(np.asarray(x), method="CD")
    np.testing.assert_allclose(float(points.discrepancy(x)), expected, rtol=1e-6, atol=1e-11)


# -------------------------------------------------------------------- errors


@pytest.mark.parametrize(
    "call, error, match",
    [
        (lambda k: points.sobol(0, 2), ValueError, "`n`"),
        (lambda k: points.sobol(4, points.SOBOL_MAX_DIM + 1), ValueError, "`d`"),
        (lambda k: points.sobol(4, 2, skip=-1), ValueError, "`skip`"),
        (lambda k: points.sobol(2**32, 1, skip=1), ValueError, "skip"),
        (lambda k: points.sobol(4.0, 2), TypeError, "`n`"),
        (lambda k: points.sobol(4, 2, key=3), TypeError, "`key`"),
        (lambda k: points.halton(4, 0), ValueError, "`d`"),
        (lambda k: points.halton(4, 2, skip=-3), ValueError, "`skip`"),
        (lambda k: points.lattice(4, points.LATTICE_MAX_DIM + 1), ValueError, "`d`"),
        (lambda k: points.stratified(k, ()), ValueError, "`counts`"),
        (lambda k: points.stratified(k, (2, 0)), ValueError, r"`counts\[1\]`"),
        (lambda k: points.stratified(k, "ab"), TypeError, "`counts`"),
        (lambda k: points.latin_hypercube(k, 0, 2), ValueError, "`n`"),
        (lambda k: points.uniform(k, 3, 2, dtype=jnp.int32), TypeError, "`dtype`"),
        (lambda k: points.lcg(-1, 3), ValueError, "`seed`"),
        (lambda k: points.lcg(0, 3, m=1), ValueError, "`m`"),
        (lambda k: points.lcg(0, 3, a=2**32), ValueError, "`a`"),
        (lambda k: points.shuffle(k, jnp.float32(1.0)), ValueError, "`x`"),
        (lambda k: points.shuffle(jax.random.split(k, 2), jnp.arange(3)), ValueError, "vmap"),
        (lambda k: points.discrepancy(jnp.ones((3,))), ValueError, "`x`"),
        (lambda k: points.discrepancy(jnp.ones((3, 2)), method="WD"), ValueError, "`method`"),
    ],
)
def test_bad_arguments(call, error, match, key):
    with pytest.raises(error, match=match):
        call(key)


def test_no_recompilation_for_new_keys(key):
    fn = jax.jit(lambda k: points.sobol(256, 3, key=k))
    fn(key)
    with jax.log_compiles(False):
        before = fn._cache_size()
        fn(jax.random.fold_in(key, 1))
        assert fn._cache_size() == before


def test_lattice_shift_keeps_structure(key):
    n = 256
    plain = np.asarray(points.lattice(n, 4))
    shifted = np.asarray(points.lattice(n, 4, key=key))
    delta = np.mod(shifted - plain, 1.0)
    np.testing.assert_allclose(delta, np.broadcast_to(delta[0], delta.shape), atol=1e-12)
    assert math.isclose(float(np.mean(points.lattice(2**12, 1))), (1 - 2**-12) / 2)
