"""Tests of `jaxmc.testing.chi2_test`: the statistic, pooling, p-values, domains, errors."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats

from jaxmc import warps
from jaxmc.testing import Chi2Table, chi2_table, chi2_test


def _uniform_interval(key, n):
    return jax.random.uniform(key, (n,), minval=-1.0, maxval=3.0)


def test_returns_plain_pair_and_matches_scipy(key):
    # A 1-D case with no pooling: the statistic and p-value are scipy's.
    result = chi2_test(key, _uniform_interval, lambda x: 0.25 * jnp.ones_like(x), (-1.0, 3.0),
                       n=4000, bins=20)
    assert isinstance(result, tuple) and len(result) == 2
    stat, p = result
    assert isinstance(stat, float) and isinstance(p, float)

    table = chi2_table(key, _uniform_interval, lambda x: 0.25 * jnp.ones_like(x), (-1.0, 3.0),
                       n=4000, bins=20)
    assert isinstance(table, Chi2Table)
    assert (table.statistic, table.p_value) == (stat, p)
    assert table.dof == 19 and table.n_pooled == 0 and table.observed.sum() == 4000
    np.testing.assert_allclose(table.expected, 200.0)
    x = np.asarray(_uniform_interval(key, 4000))
    observed, _ = np.histogram(x, bins=20, range=(-1.0, 3.0))
    np.testing.assert_array_equal(table.observed, observed)
    ref = scipy.stats.chisquare(observed, table.expected)
    assert stat == pytest.approx(ref.statistic, rel=1e-10)
    assert p == pytest.approx(ref.pvalue, rel=1e-8)


def test_pooling_of_small_cells(key):
    # An exponential tail on a long interval: most cells expect < 5 samples and are pooled.
    table = chi2_table(
        key,
        lambda k, n: warps.exponential(jax.random.uniform(k, (n,)), 1.0),
        lambda x: warps.exponential_pdf(x, 1.0),
        (0.0, 40.0),
        n=2000,
        bins=200,
    )
    assert table.n_pooled > 100
    large = int(np.sum(table.expected >= 5))
    small_total = float(np.sum(table.expected[table.expected < 5]))
    # every pooled group holds >= 5 expected samples; the remainder joins another cell
    assert large + 1 <= table.dof + 1 <= large + small_total // 5
    assert table.expected.sum() == pytest.approx(2000, rel=1e-6)
    assert table.p_value > 1e-3, table.report()


def test_p_values_are_calibrated():
    # Under the null hypothesis the p-value is uniform: KS test over 25 independent keys.
    def sample(k, n):
        return warps.hemisphere_cosine(jax.random.uniform(k, (n, 2)))

    # Same `sample` and `pdf` objects each time: compiled once.
    ps = [
        chi2_test(jax.random.fold_in(jax.random.key(5), i), sample, warps.hemisphere_cosine_pdf,
                  "hemisphere", n=3000, bins=8)[1]
        for i in range(25)
    ]
    assert scipy.stats.kstest(ps, "uniform").pvalue > 1e-3, ps


def test_uniform_densities_on_every_domain(key):
    # The parameterisations' Jacobians are right: uniform densities integrate to 1 and pass.
    cases = [
        ("square", lambda k, n: jax.random.uniform(k, (n, 2)), lambda x: 1.0),
        ("disk", lambda k, n: warps.disk_polar(jax.random.uniform(k, (n, 2))), lambda x: 1 / math.pi),
        ("sphere", lambda k, n: warps.sphere_uniform(jax.random.uniform(k, (n, 2))),
         lambda x: 1 / (4 * math.pi)),
        ("hemisphere", lambda k, n: warps.hemisphere_uniform(jax.random.uniform(k, (n, 2))),
         lambda x: 1 / (2 * math.pi)),
        ("triangle", lambda k, n: warps.triangle(jax.random.uniform(k, (n, 2))), lambda x: 2.0),
        (((0.0, -2.0), (0.5, 2.0)),
         lambda k, n: jnp.stack([0.5 * jax.random.uniform(k, (n,)),
                                 4.0 * jax.random.uniform(jax.random.fold_in(k, 1), (n,)) - 2.0],
                                axis=-1),
         lambda x: 0.5),
    ]
    for i, (domain, sample, pdf) in enumerate(cases):
        table = chi2_table(jax.random.fold_in(key, i), sample, lambda x, pdf=pdf: pdf(x) + 0 * x[0],
                           domain, n=5000, bins=10)
        assert table.pdf_integral == pytest.approx(1.0, abs=1e-12), domain
        assert table.p_value > 1e-4, f"{domain}\n{table.report()}"


def test_samples_outside_the_domain_reject(key):
    def sample(k, n):
        return jax.random.uniform(k, (n,), minval=0.0, maxval=1.01)  # 1% beyond the interval

    table = chi2_table(key, sample, lambda x: jnp.ones_like(x), (0.0, 1.0), n=2000, bins=10)
    assert table.n_outside > 0
    assert table.statistic == math.inf and table.p_value == 0.0
    # Non-finite samples count as outside too.
    stat, p = chi2_test(key, lambda k, n: jnp.full((n,), jnp.nan), lambda x: jnp.ones_like(x),
                        (0.0, 1.0), n=100, bins=2)
    assert p == 0.0


def test_samples_where_pdf_is_zero_reject(key):
    # Uniform sphere samples against a density that claims the lower hemisphere is empty.
    def sample(k, n):
        return warps.sphere_uniform(jax.random.uniform(k, (n, 2)))

    stat, p = chi2_test(key, sample, lambda w: jnp.where(w[2] > 0, 1 / (2 * math.pi), 0.0),
                        "sphere", n=2000, bins=8)
    assert stat == math.inf and p == 0.0


def test_a_slightly_wrong_density_is_detected(key):
    # power(u, 2) sampled, pdf of power 2.1 claimed: a 3% effect needs enough samples.
    def sample(k, n):
        return warps.power(jax.random.uniform(k, (n,)), 2.0)

    _, p_right = chi2_test(key, sample, lambda x: warps.power_pdf(x, 2.0), (0.0, 1.0),
                           n=200_000, bins=50)
    _, p_wrong = chi2_test(key, sample, lambda x: warps.power_pdf(x, 2.1), (0.0, 1.0),
                           n=200_000, bins=50)
    assert p_right > 1e-4 and p_wrong < 1e-10


def test_report_prints_observed_and_expected(key):
    table = chi2_table(key, _uniform_interval, lambda x: 0.25, (-1.0, 3.0), n=1000, bins=5)
    text = table.report(top=3)
    assert "observed" in text and "expected" in text and "dof = 4" in text


def test_float32_samples(key):
    def sample(k, n):
        return warps.hemisphere_cosine(jax.random.uniform(k, (n, 2), dtype=jnp.float32))

    table = chi2_table(key, sample, warps.hemisphere_cosine_pdf, "hemisphere", n=20_000, bins=12)
    assert table.n_outside == 0 and table.p_value > 1e-4, table.report()


def test_non_jittable_sampler(key):
    rng = np.random.default_rng(0)
    stat, p = chi2_test(key, lambda k, n: rng.random(n), lambda x: jnp.ones_like(x), (0.0, 1.0),
                        n=1000, bins=10, jit=False)
    assert p > 1e-4


def test_bad_arguments_raise(key):
    ok_sample = lambda k, n: jax.random.uniform(k, (n, 2))
    ok_pdf = lambda x: 1.0 + 0 * x[0]
    with pytest.raises(ValueError, match="`domain`"):
        chi2_test(key, ok_sample, ok_pdf, "torus", n=100, bins=4)
    with pytest.raises(ValueError, match="`domain`"):
        chi2_test(key, ok_sample, ok_pdf, (1.0, 0.0), n=100, bins=4)
    with pytest.raises(ValueError, match="`sample"):
        chi2_test(key, ok_sample, ok_pdf, "sphere", n=100, bins=4)
    with pytest.raises(ValueError, match="`pdf`"):
        chi2_test(key, ok_sample, lambda x: jnp.ones(3), "square", n=100, bins=4)
    with pytest.raises(ValueError, match="`bins`"):
        chi2_test(key, ok_sample, ok_pdf, "square", n=100, bins=(4, 4, 4))
    with pytest.raises(ValueError, match="`n`"):
        chi2_test(key, ok_sample, ok_pdf, "square", n=0, bins=4)
    with pytest.raises(ValueError, match="increase"):
        chi2_test(key, ok_sample, ok_pdf, "square", n=4, bins=4)
    with pytest.raises(TypeError, match="`key`"):
        chi2_test(0, ok_sample, ok_pdf, "square", n=100, bins=4)
