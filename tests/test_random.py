"""Tests of `jaxmc._random`: Threefry against reference values, uniformity, permutations.

Statistical checks use fixed keys and a p-value floor of 1e-4, Bonferroni-corrected
where one test makes several checks.
"""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.extend.random import threefry_2x32
from scipy import stats

from jaxmc import _random, points  # `_random` is private: this file tests it directly
from jaxmc._points import _random_sets  # private: forces latin_hypercube's permutation path

from .helpers import P_FLOOR, assert_uniform, one_per_bin, run_keys


# Random123's known-answer vectors for Threefry-2x32-20: (key, counter) -> output.
KNOWN_ANSWERS = [
    ((0x00000000, 0x00000000), (0x00000000, 0x00000000), (0x6B200159, 0x99BA4EFE)),
    ((0xFFFFFFFF, 0xFFFFFFFF), (0xFFFFFFFF, 0xFFFFFFFF), (0x1CB996FC, 0xBB002BE7)),
    ((0x13198A2E, 0x03707344), (0x243F6A88, 0x85A308D3), (0xC4923A9C, 0x483DF7A0)),
]


@pytest.mark.parametrize("key_words, counter, expected", KNOWN_ANSWERS)
def test_threefry_known_answers(key_words, counter, expected):
    k0, k1 = (jnp.uint32(w) for w in key_words)
    x0, x1 = (jnp.uint32(w) for w in counter)
    out = _random.threefry2x32(k0, k1, x0, x1)
    assert tuple(int(w) for w in out) == expected


def test_threefry_matches_jax():
    words = jax.random.bits(jax.random.key(1), (2,), jnp.uint32)
    count = jax.random.bits(jax.random.key(2), (2, 1000), jnp.uint32)
    a, b = _random.threefry2x32(words[0], words[1], count[0], count[1])
    ref = threefry_2x32(words, count.reshape(-1))
    np.testing.assert_array_equal(np.concatenate([a, b]), ref)


@pytest.mark.parametrize("dtype", [jnp.float16, jnp.float32, jnp.float64])
def test_uniform_is_uniform_in_unit_interval(key, dtype):
    u = _random.uniform(key, (50_000, 3), dtype)
    assert u.dtype == dtype and u.shape == (50_000, 3)
    u = np.asarray(u, np.float64)
    assert_uniform(u, dtype)
    # Neighbouring entries (consecutive counters) are independent.
    pairs = np.floor(u[:, :2] * 8).astype(int)
    table = np.zeros((8, 8))
    np.add.at(table, (pairs[:, 0], pairs[:, 1]), 1)
    assert stats.chi2_contingency(table).pvalue > P_FLOOR


def test_uniform_float64_uses_53_bits(key):
    u = np.asarray(_random.uniform(key, (4096,), jnp.float64))
    # float32-style generation would leave the low 29 bits of every mantissa zero.
    low_bits = (u * 2.0**53).astype(np.int64) & ((1 << 29) - 1)
    assert np.count_nonzero(low_bits) > 4000


def test_bits_depend_on_key_and_are_balanced():
    a = np.asarray(_random.bits(jax.random.key(0), (100_001,)))
    b = np.asarray(_random.bits(jax.random.key(1), (100_001,)))
    assert a.dtype == np.uint32 and a.shape == (100_001,)
    assert np.mean(a == b) < 1e-3
    # Every bit position is a fair coin: binomial z-scores within 5 sigma.
    ones = ((a[:, None] >> np.arange(32, dtype=np.uint32)) & 1).sum(axis=0)
    z = (ones - a.size / 2) / np.sqrt(a.size / 4)
    assert np.abs(z).max() < 5, z


def test_streams_differ_from_jax_random(key):
    ours = np.asarray(_random.bits(key, (64,)))
    theirs = np.asarray(jax.random.bits(key, (64,), jnp.uint32))
    assert not np.any(ours == theirs)


def test_jit_and_vmap_agree(key):
    keys = jax.random.split(key, 3)
    batched = jax.vmap(lambda k: _random.uniform(k, (10, 2), jnp.float32))(keys)
    for i in range(3):
        np.testing.assert_array_equal(batched[i], _random.uniform(keys[i], (10, 2), jnp.float32))
    jitted = jax.jit(lambda k: _random.bits(k, (7, 3)))(key)
    np.testing.assert_array_equal(jitted, _random.bits(key, (7, 3)))


@pytest.mark.parametrize("n", [1, 2, 5, 64, 1000, 4097, 2**16 + 3])
def test_permute_is_a_bijection(key, n):
    index = jnp.arange(n, dtype=jnp.uint32)
    perm = np.asarray(_random.permute(key, index, n))
    np.testing.assert_array_equal(np.sort(perm), np.arange(n))
    if n > 64:
        assert np.mean(perm == np.arange(n)) < 0.01


@pytest.mark.parametrize("n", [3, 5, 6, 8, 13])
def test_permute_each_image_exactly_uniform(n):
    # pi(0) and pi(n - 1) over many keys: uniform on the n bins (2 checks).
    ends = jnp.array([0, n - 1], jnp.uint32)
    images = np.asarray(run_keys(lambda k: _random.permute(k, ends, n), 5, k=20_000))
    for column in images.T:
        counts = np.bincount(column, minlength=n)
        assert stats.chisquare(counts).pvalue > P_FLOOR / 2, counts


def test_permute_streams_are_independent():
    # (pi_0(0), pi_1(0)) for two streams of one key: uniform on 5 x 5 cells.
    n = 5
    streams = jnp.arange(2, dtype=jnp.uint32)
    image = lambda k: _random.permute(k, jnp.zeros(2, jnp.uint32), n, stream=streams)
    pairs = np.asarray(run_keys(image, 6, k=20_000))
    counts = np.bincount(pairs[:, 0] * n + pairs[:, 1], minlength=n * n)
    assert stats.chisquare(counts).pvalue > P_FLOOR, counts


def test_permute_reaches_every_small_permutation():
    # n = 4 is a power of two, where balanced Feistel maps alone are even permutations;
    # the uniform rotation makes all 24 reachable.
    perms = run_keys(lambda k: _random.permute(k, jnp.arange(4, dtype=jnp.uint32), 4), 7, k=4000)
    seen = {tuple(p) for p in np.asarray(perms).tolist()}
    assert seen == set(itertools.permutations(range(4)))


def test_latin_hypercube_large_n_uses_permutations(key):
    n = 2**16 + 5
    x = np.asarray(points.latin_hypercube(key, n, 3))
    assert one_per_bin(x, n)
    cells = np.floor(x * n).astype(np.int64)
    # Axes are permuted independently: the bins of axes 0 and 1 are uncorrelated.
    assert abs(stats.pearsonr(cells[:, 0], cells[:, 1]).statistic) < 5 / np.sqrt(n)


def test_latin_hypercube_permutation_path_is_marginally_uniform(monkeypatch):
    # Force the permutation path at a small n and test point 0's bin over keys.
    monkeypatch.setattr(_random_sets, "_LHS_SORT_MAX", 1)
    n = 7
    lhs = _random_sets._latin_hypercube
    # It is jitted: a trace cached by an earlier test would ignore the patched threshold,
    # and the one made here must not outlive the patch.
    lhs.clear_cache()
    try:
        x = run_keys(lambda k: lhs(k, n, 2, jnp.dtype(jnp.float64)), 8, k=14_000)
    finally:
        lhs.clear_cache()
    bins = np.floor(np.asarray(x[:, 0, :]) * n).astype(int)
    for j in range(2):
        counts = np.bincount(bins[:, j], minlength=n)
        assert stats.chisquare(counts).pvalue > P_FLOOR / 2, counts


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_categorical_draws_indices_with_the_softmax_probabilities(key, dtype):
    # Inverse-CDF categorical: the counts of 2e5 draws against softmax(log_weights),
    # a zero-probability index never drawn, the last index reachable.
    probs = np.array([0.5, 0.0, 0.2, 0.05, 0.25])
    with np.errstate(divide="ignore"):
        log_weights = jnp.asarray(np.log(probs) + 3.0, dtype)  # unnormalised
    n = 200_000
    k = _random.categorical(key, log_weights, n)
    assert k.dtype == jnp.int32 and k.shape == (n,)
    counts = np.bincount(np.asarray(k), minlength=5)
    assert counts[1] == 0 and counts[4] > 0
    keep = probs > 0
    assert stats.chisquare(counts[keep], n * probs[keep]).pvalue > P_FLOOR
    assert int(jnp.max(jax.jit(_random.categorical, static_argnums=2)(key, log_weights, 10))) < 5
