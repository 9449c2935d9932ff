import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats

from jaxmc.stats import (
    Combined,
    Estimate,
    combine,
    merge,
    merge_all,
    moments,
    student_t_quantile,
)


def _estimate(mean, variance, n=100):
    return Estimate(jnp.asarray(mean), jnp.asarray(variance), jnp.asarray(n), jnp.asarray(0))


def test_interval_and_chebyshev_match_formulas():
    est = _estimate(2.0, 0.25)
    low, high = est.interval(0.95)
    z = scipy.stats.norm.ppf(0.975)
    np.testing.assert_allclose([low, high], [2 - z * 0.5, 2 + z * 0.5], rtol=1e-12)
    # eq. 14: eps = sqrt(V / delta)
    np.testing.assert_allclose(est.chebyshev(0.05), np.sqrt(0.25 / 0.05), rtol=1e-12)
    np.testing.assert_allclose(est.stderr, 0.5)


def test_interval_is_student_t_with_the_estimates_degrees_of_freedom():
    few = Estimate(jnp.asarray(2.0), jnp.asarray(0.25), jnp.asarray(100), jnp.asarray(0),
                   dof=jnp.asarray(4.0))
    low, high = few.interval(0.954)
    t = scipy.stats.t.ppf(0.977, 4)
    np.testing.assert_allclose([low, high], [2 - t * 0.5, 2 + t * 0.5], rtol=1e-9)
    assert "dof=4" in repr(few)
    # An Estimate built without `dof` is normal (the default, infinite) and says nothing.
    normal = _estimate(2.0, 0.25)
    assert np.isposinf(normal.dof) and "dof" not in repr(normal)


def test_student_t_quantile_matches_scipy():
    for dof in (1, 2, 3, 7, 31, 200):
        for p in (0.6, 0.9, 0.975, 0.995, 0.05):
            np.testing.assert_allclose(
                student_t_quantile(p, dof), scipy.stats.t.ppf(p, dof), rtol=1e-9, atol=1e-12
            )


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_student_t_quantile_is_symmetric_and_normal_at_infinite_dof(dtype):
    p = jnp.asarray([0.6, 0.977, 0.9995], dtype)
    for dof in (1.0, 4.0, 30.0):
        q = student_t_quantile(p, jnp.asarray(dof, dtype))
        assert q.dtype == dtype
        np.testing.assert_allclose(q, scipy.stats.t.ppf(np.asarray(p, float), dof), rtol=1e-4)
        np.testing.assert_allclose(student_t_quantile(1 - p, dof), -q, rtol=1e-4)
    np.testing.assert_allclose(student_t_quantile(p, jnp.inf),
                               scipy.stats.norm.ppf(np.asarray(p, float)), rtol=1e-5)


def test_combine_counts_degrees_of_freedom_by_satterthwaite():
    def part(dof):
        return Estimate(jnp.asarray(1.0), jnp.asarray(0.01), jnp.asarray(100), jnp.asarray(0),
                        dof=jnp.asarray(dof))

    # Equal variances of 4 dof each: (2V)^2 / (2 V^2 / 4) = 8.
    np.testing.assert_allclose(combine([part(4.0), part(4.0)]).dof, 8.0, rtol=1e-12)
    # A normal part adds no uncertainty of its own: (2V)^2 / (V^2 / 4) = 16.
    np.testing.assert_allclose(combine([part(4.0), part(jnp.inf)]).dof, 16.0, rtol=1e-12)
    assert np.isposinf(combine([part(jnp.inf), part(jnp.inf)]).dof)


@pytest.mark.parametrize("bad", [0.0, 1.0, 1.5, -0.1])
def test_interval_rejects_bad_level(bad):
    with pytest.raises(ValueError, match="level"):
        _estimate(0.0, 1.0).interval(bad)


@pytest.mark.parametrize("bad", [0.0, 1.5])
def test_chebyshev_rejects_bad_delta(bad):
    with pytest.raises(ValueError, match="delta"):
        _estimate(0.0, 1.0).chebyshev(bad)


def test_combine_inverse_variance_weights_and_chi2():
    means = np.array([1.0, 1.2, 0.9])
    variances = np.array([0.01, 0.04, 0.02])
    out = combine([_estimate(m, v) for m, v in zip(means, variances)])
    assert isinstance(out, Combined)
    w = 1 / variances
    mean = np.sum(w * means) / np.sum(w)
    chi2 = np.sum(w * (means - mean) ** 2)
    np.testing.assert_allclose(out.mean, mean, rtol=1e-12)
    np.testing.assert_allclose(out.variance, 1 / np.sum(w), rtol=1e-12)
    np.testing.assert_allclose(out.chi2_dof, chi2 / 2, rtol=1e-12)
    np.testing.assert_allclose(out.q, scipy.stats.chi2.sf(chi2, 2), rtol=1e-10)
    assert out.n == 300
    np.testing.assert_allclose(out.parts.mean, means)


def test_combine_stacked_vector_valued():
    stacked = Estimate(
        jnp.array([[1.0, 2.0], [1.1, 2.2]]),
        jnp.array([[0.01, 0.04], [0.01, 0.04]]),
        jnp.array([10, 10]),
        jnp.array([0, 1]),
    )
    out = combine(stacked)
    np.testing.assert_allclose(out.mean, [1.05, 2.1])
    np.testing.assert_allclose(out.variance, [0.005, 0.02])
    chi2 = 0.05**2 / 0.01 * 2 + 0.1**2 / 0.04 * 2
    np.testing.assert_allclose(out.chi2_dof, chi2 / 2)  # (k - 1) * 2 components
    assert out.n_nonfinite == 1


def test_combine_is_calibrated_for_agreeing_parts():
    # Parts drawn from their stated error bars: q must be uniform, chi2_dof near 1.
    key = jax.random.key(3)
    k, parts = 4000, 5
    sigma = jnp.array([0.1, 0.2, 0.3, 0.4, 0.5])
    means = 1.0 + sigma * jax.random.normal(key, (k, parts))

    def one(m):
        return combine(Estimate(m, sigma**2, jnp.full(parts, 10), jnp.zeros(parts, int)))

    out = jax.vmap(one)(means)
    np.testing.assert_allclose(jnp.mean(out.chi2_dof), 1.0, atol=5 * np.sqrt(2 / 4 / k))
    assert scipy.stats.kstest(np.asarray(out.q), "uniform").pvalue > 1e-4
    z = (out.mean - 1.0) / out.stderr
    np.testing.assert_allclose(jnp.std(z), 1.0, atol=5 / np.sqrt(2 * k))


def test_combine_zero_variance_parts():
    def est(mean, var):
        return Estimate(jnp.asarray(mean), jnp.asarray(var), jnp.asarray(100), jnp.asarray(0))

    # An exact part (zero variance, non-zero mean) takes all the weight.
    c = combine([est(1.0, 0.04), est(2.0, 0.0), est(3.0, 0.01)])
    assert float(c.mean) == 2.0 and float(c.variance) == 0.0
    # An all-zero part (a round that missed the peak) carries no information: it is left
    # out, and the chi2 has one degree of freedom (two measured parts).
    c = combine([est(1.0, 0.04), est(0.0, 0.0), est(1.2, 0.04)])
    np.testing.assert_allclose(c.mean, 1.1)
    np.testing.assert_allclose(c.variance, 0.02)
    np.testing.assert_allclose(c.chi2_dof, (0.1**2 / 0.04) * 2)
    np.testing.assert_allclose(c.q, scipy.stats.chi2.sf(0.5, 1))
    # Nothing but empty parts: zero, with zero variance and no degrees of freedom.
    c = combine([est(0.0, 0.0), est(0.0, 0.0)])
    assert float(c.mean) == 0.0 and float(c.variance) == 0.0
    assert float(c.chi2_dof) == 0.0 and float(c.q) == 1.0
    # A part of unknown (infinite) variance gets no weight; with nothing else, nothing is known.
    c = combine([est(1.0, 0.04), est(5.0, jnp.inf)])
    assert float(c.mean) == 1.0 and float(c.variance) == 0.04
    c = combine([est(1.0, jnp.inf), est(0.0, 0.0)])
    assert bool(jnp.isnan(c.mean)) and float(c.variance) == float("inf")


def test_combine_sequential_weights_each_part_by_the_variance_before_it():
    means, variances = np.array([1.0, 2.0, 3.0]), np.array([1.0, 4.0, 1.0])
    out = combine([_estimate(m, v) for m, v in zip(means, variances)], sequential=True)
    w = np.array([1 / 1.0, 1 / 1.0, 1 / 4.0])  # own, then the previous part's
    np.testing.assert_allclose(out.mean, np.sum(w * means) / np.sum(w), rtol=1e-12)
    np.testing.assert_allclose(out.variance, np.sum(w**2 * variances) / np.sum(w) ** 2, rtol=1e-12)
    assert out.sequential and "wgt average" in out.summary()
    # A round that saw nothing (0 +- 0) has no weight and lends none: the next is weighed by
    # the last measured round.
    out = combine([_estimate(1.0, 1.0), _estimate(0.0, 0.0), _estimate(2.0, 4.0)], sequential=True)
    np.testing.assert_allclose(out.mean, 1.5)


def test_combine_sequential_removes_most_of_the_bias_of_own_variances():
    # Skewed parts whose variance grows with the value (a round that starved a region
    # reports a low value and a small variance): each part is exponential with mean 1 and a
    # variance estimate equal to its square. Inverse-variance weights then favour the low
    # parts (measured: 81% low); weights from the part before do not depend on the part,
    # and what bias is left comes from normalising by their sum (measured: 3% high).
    rng = np.random.default_rng(0)
    k, parts = 20_000, 8
    values = rng.exponential(1.0, (k, parts))
    full = lambda v: jnp.full((k, parts), v)  # noqa: E731
    stacked = Estimate(jnp.asarray(values), jnp.asarray(values**2), full(10), full(0),
                       ess=full(10.0), n_nonzero=full(10), pareto_k=full(0.0), conservative=full(False),
                       dof=full(jnp.inf))
    bias = {}
    for sequential in (False, True):
        out = jax.vmap(lambda e: combine(e, sequential=sequential))(stacked)
        error = np.asarray(out.mean) - 1.0
        bias[sequential] = (np.mean(error), np.std(error) / np.sqrt(k))
    (own, _), (seq, seq_se) = bias[False], bias[True]
    assert own < -0.5 and abs(own) > 10 * (abs(seq) + 5 * seq_se), bias
    assert abs(seq) < 0.05, bias


def test_combine_sequential_scales_the_weights_by_part_size():
    # A part of 4x the evaluations is expected to have a quarter of the variance per
    # evaluation the part before it measured: weight 4 / V_before.
    parts = [Estimate(jnp.asarray(m), jnp.asarray(v), jnp.asarray(n), jnp.asarray(0))
             for m, v, n in ((1.0, 1.0, 100), (2.0, 2.0, 100), (3.0, 0.5, 400))]
    out = combine(parts, sequential=True)
    w = np.array([1 / 1.0, 1 / 1.0, 4 / 2.0])
    np.testing.assert_allclose(out.mean, np.sum(w * [1.0, 2.0, 3.0]) / np.sum(w), rtol=1e-12)


def test_combine_rejects_bad_input():
    with pytest.raises(TypeError, match="estimates"):
        combine([])
    with pytest.raises(ValueError, match="stacked"):
        combine(_estimate(1.0, 1.0))


def test_chan_merge_is_exact():
    x = np.random.default_rng(0).normal(3.0, 2.0, size=(1000, 3))
    a, b = moments(jnp.asarray(x[:300])), moments(jnp.asarray(x[300:]))
    m = merge(a, b)
    np.testing.assert_allclose(m.mean, x.mean(0), rtol=1e-12)
    np.testing.assert_allclose(m.m2, ((x - x.mean(0)) ** 2).sum(0), rtol=1e-10)
    parts = [moments(jnp.asarray(c)) for c in np.split(x, 8)]
    stacked = jax.tree.map(lambda *t: jnp.stack(t[:7]), *parts)  # 7: an odd tree
    x = x[:875]
    tree = merge_all(stacked)
    np.testing.assert_allclose(tree.count, 875)
    np.testing.assert_allclose(tree.m2, ((x - x.mean(0)) ** 2).sum(0), rtol=1e-10)


def test_merge_with_empty_side():
    a = moments(jnp.arange(5.0))
    empty = moments(jnp.arange(5.0), mask=jnp.zeros(5, bool))
    for m in (merge(a, empty), merge(empty, a)):
        np.testing.assert_allclose(m.mean, 2.0)
        np.testing.assert_allclose(m.m2, 10.0)


def test_the_rounds_scatter_bound_holds_as_often_as_chi_square_says():
    # Five rounds' means, normal about 2 with a per-evaluation relative variance of 0.3 (rounds
    # of 1000): the bound z = 2 log-standard-deviations above the scatter falls below the truth
    # when chi2_4 / 4 < exp(-2 sqrt(psi'(2))), a probability of 0.0618; over 4000 draws, within
    # 5 binomial standard errors. Rounds before the last five, off the mark, do not count.
    from jaxmc._stats import scatter_bound

    truth, size, draws = 0.3, 1000, 4000
    sd = 2.0 * np.sqrt(truth / size)
    means = 2.0 + sd * jax.random.normal(jax.random.key(3), (draws, 8))
    means = means.at[:, :3].add(1.0)  # (earlier rounds, off the mark: not counted)
    bounds = np.asarray(jax.vmap(lambda m: scatter_bound(m, size, 2.0))(means))
    cutoff = 4 * np.exp(-2 * np.sqrt(float(jax.scipy.special.polygamma(1, 2.0))))
    p = scipy.stats.chi2.cdf(cutoff, 4)
    assert abs(np.mean(bounds < truth) - p) < 5 * np.sqrt(p * (1 - p) / draws)
    assert np.isinf(scatter_bound(jnp.array([1.0, jnp.nan, 1.0]), size, 2.0))
    assert np.isinf(scatter_bound(jnp.array([1.0]), size, 2.0))
