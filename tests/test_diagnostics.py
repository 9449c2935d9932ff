"""Diagnostics on every estimate: ess, non-zero count, Pareto tail, rounding floors, warnings."""

import contextlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats as sps

import jaxmc
from jaxmc import stats
from jaxmc._diagnostics import TAIL, merge_tails, pareto_k, power_law_tail, tail_of


@pytest.mark.parametrize("k", [-0.3, 0.3, 0.7, 1.0])
def test_pareto_k_recovers_the_generalised_pareto_shape(k):
    # k-hat from the largest TAIL of 20,000 values has sd ~0.1; over 20 samples the mean's
    # is ~0.025, and the prior (10 observations at 1/2) shifts it by at most 0.07 here.
    rng = np.random.default_rng(7)
    fits = [
        float(pareto_k(tail_of(jnp.asarray(sps.genpareto.rvs(k, size=20_000, random_state=rng),
                                           jnp.float32))))
        for _ in range(20)
    ]
    assert abs(np.mean(fits) - k) < 0.2
    assert abs(np.mean(fits) - (k + 0.07 * (0.5 - k))) < 0.1


def test_pareto_k_separates_finite_from_infinite_variance():
    keys = jax.random.split(jax.random.key(1), 50)

    def fits(power):
        def one(key):
            return pareto_k(tail_of(jax.random.uniform(key, (2**16,), minval=1e-12) ** -power))

        return np.asarray(jax.vmap(one)(keys))

    # u^-a has tail index 1/a: k = a. Measured over 200 keys: k-hat 0.35 +- 0.11 (a = 1/3,
    # none above 0.7), 0.86 +- 0.15 (a = 0.9, 87% above 0.7).
    finite, infinite = fits(1 / 3), fits(0.9)
    assert abs(finite.mean() - 1 / 3) < 0.1 and np.mean(finite > 0.7) <= 0.04
    assert abs(infinite.mean() - 0.9) < 0.15 and np.mean(infinite > 0.7) >= 0.6
    assert float(pareto_k(tail_of(jnp.cos(jnp.linspace(0, 1, 4096))))) < 0  # bounded
    assert np.isneginf(float(pareto_k(tail_of(jnp.ones(1000)))))  # a flat top: no tail
    assert np.isnan(float(pareto_k(tail_of(jnp.arange(10.0)))))  # too few values to fit


def test_tails_merge_exactly():
    y = jax.random.normal(jax.random.key(2), (3000, 2))
    whole = tail_of(y)
    merged = merge_tails(tail_of(y[:1000]), tail_of(y[1000:]))
    for a, b in zip(whole, merged):
        np.testing.assert_allclose(a, b, rtol=1e-5)
    assert whole.top.shape == (2, TAIL + 1)



@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("n", [5000, 2**14 + 3])
def test_tail_keeps_the_largest_values_exactly(dtype, n):
    # float64 values are ranked in float32 (a full sort otherwise): the kept values must
    # still be the largest, in full precision, decreasing; with values spanning 1e300,
    # values that differ only beyond float32's precision, zeros and fewer values than kept.
    # A stream's block (2^14 and more) is searched group by group first: the same values.
    rng = np.random.default_rng(3)
    wide = rng.pareto(0.05, n) if dtype == jnp.float64 else rng.pareto(0.5, n)
    close = 1.0 + rng.integers(0, 50, n) * 1e-12 if dtype == jnp.float64 else rng.random(n)
    sparse = np.where(rng.random(n) < 0.01, rng.random(n), 0.0)
    for c in (wide, close, -wide, sparse, rng.random(40)):
        top = np.asarray(tail_of(jnp.asarray(c, dtype)).top)
        expected = np.sort(np.abs(np.asarray(c, dtype)))[::-1][: TAIL + 1]
        np.testing.assert_array_equal(top[: expected.size], expected)
        assert np.all(top[expected.size :] == 0)

def test_ess_and_nonzero_count():
    est = jaxmc.uniform(jax.random.key(0), lambda x: 2.0, 0.0, 1.0, 1000)
    assert float(est.ess) == pytest.approx(1000, rel=1e-5)
    assert int(est.n_nonzero) == 1000
    with pytest.warns(jaxmc.ReliabilityWarning, match="non-zero"):
        est = jaxmc.uniform(jax.random.key(0), lambda x: jnp.where(x < 0.003, 1.0, 0.0), 0.0, 1.0,
                            2000)  # ~6 hits
    assert 0 < int(est.n_nonzero) < 10
    assert float(est.ess) == pytest.approx(int(est.n_nonzero), rel=1e-5)


def test_array_valued_diagnostics_are_per_component():
    est = jaxmc.uniform(jax.random.key(0), lambda x: jnp.stack([x, 1.0 + 0 * x]), 0.0, 1.0, 4096)
    assert est.ess.shape == est.pareto_k.shape == est.n_nonzero.shape == (2,)
    assert float(est.ess[1]) == pytest.approx(4096, rel=1e-5)
    assert 0.7 * 4096 < float(est.ess[0]) < 0.8 * 4096  # (E x)^2 / E x^2 = 3/4


@pytest.mark.parametrize("method", ["plain", "qmc", "adaptive", "auto"])
def test_integrate_warns_on_a_missed_peak(method):
    def peak(x):
        return jnp.exp(-jnp.sum((x - 0.3) ** 2) / (2 * 1e-4**2))

    with pytest.warns(jaxmc.ReliabilityWarning):
        est = jaxmc.integrate(jax.random.key(3), peak, [0.0] * 3, [1.0] * 3, n=2**15, method=method)
    assert bool(stats.unreliable(est))


@pytest.mark.parametrize("method", ["plain", "qmc"])
def test_integrate_flags_an_infinite_variance_tail(method):
    # x^-0.9 on (0, 1]: integral 10, tail index 1/0.9 (k = 0.9): the variance is infinite.
    # (A VEGAS grid confines the tail to its first bin, where k-hat sees it on some keys only.)
    with pytest.warns(jaxmc.ReliabilityWarning, match="Pareto"):
        est = jaxmc.integrate(jax.random.key(4), lambda x: x[0] ** -0.9, [0.0], [1.0], n=2**18,
                              method=method)
    assert float(est.pareto_k) > 0.7


def test_no_false_alarms_on_benign_integrands():
    # pytest turns warnings into errors: none may be raised here.
    key = jax.random.key(5)
    genz = lambda x: jnp.exp(-jnp.sum(25.0 * (x - 0.5) ** 2))  # noqa: E731
    lo, hi = [0.0] * 3, [1.0] * 3
    for method in ["plain", "qmc", "adaptive"]:
        est = jaxmc.integrate(key, genz, lo, hi, n=2**15, method=method)
        assert not bool(stats.unreliable(est)), (method, stats.reliability_reasons(est))
    for est in (jaxmc.uniform(key, genz, lo, hi, 4096), jaxmc.randomized_qmc(key, genz, lo, hi, 1024),
                jaxmc.stratified(key, genz, lo, hi, (8,) * 3), jaxmc.antithetic(key, genz, lo, hi, 4096)):
        assert not bool(stats.unreliable(est)), stats.reliability_reasons(est)
    jaxmc.fit.adapt(key, genz, jaxmc.proposals.Grid(lo, hi), iterations=5, n_per_iteration=2**12)
    # An integrable singularity (finite variance) is benign for i.i.d. sampling.
    singular = lambda x: x[0] ** (-1 / 3)  # noqa: E731
    est = jaxmc.integrate(key, singular, [0.0], [1.0], n=2**15, method="plain")
    assert not bool(stats.unreliable(est)), stats.reliability_reasons(est)
    assert not bool(stats.unreliable(jaxmc.uniform(key, singular, [0.0], [1.0], 4096)))


def test_structured_error_bars_under_a_power_law_tail_are_flagged_as_bounds():
    # x^-1/3 on (0, 1] (integral 3/2): strata, replicas and antithetic pairs see the
    # singularity in one cell, so their spread is skewed; the i.i.d. variance bounds the error
    # instead, several times too wide (2-sigma coverage 1.00), and the result says so.
    key = jax.random.key(5)
    singular = lambda x: x[0] ** (-1 / 3)  # noqa: E731
    runs = {
        "integrate qmc": lambda: jaxmc.integrate(key, singular, [0.0], [1.0], n=2**15, method="qmc"),
        "randomized_qmc": lambda: jaxmc.randomized_qmc(key, singular, [0.0], [1.0], 1024),
        "stratified": lambda: jaxmc.stratified(key, singular, [0.0], [1.0], (4096,)),
        # VEGAS+ rounds are stratified too: here every round is bounded.
        "fit.adapt": lambda: jaxmc.fit.adapt(key, singular, jaxmc.proposals.Grid([0.0], [1.0]),
                                             iterations=8, n_per_iteration=2048)[0],
    }
    for name, run in runs.items():
        warns = name in ("integrate qmc", "fit.adapt")  # the estimators that warn
        with pytest.warns(jaxmc.ReliabilityWarning, match="upper bound") if warns \
                else contextlib.nullcontext():
            est = run()
        assert bool(jnp.all(est.conservative)), name
        assert bool(stats.unreliable(est)), name
        assert abs(float(est.mean) - 1.5) < 2 * float(est.stderr), name


def test_a_bounded_integrand_keeps_its_stratified_error_bar():
    # exp(x0 + x1/2) on the unit square, 8x8 strata of 2 points (and 16x16): k-hat on the few
    # largest of 128 values is noise, which must not swap stratification's error bar for the
    # i.i.d. bound. Over 4000 keys the reported variance is the means' variance (its
    # estimate's sd ~2%).
    f = lambda x: jnp.exp(x[0] + x[1] / 2)  # noqa: E731
    for counts in ((8, 8), (16, 16)):
        keys = jax.random.split(jax.random.key(0), 4000)
        est = jax.jit(jax.vmap(lambda k: jaxmc.stratified(k, f, jnp.zeros(2), jnp.ones(2),
                                                           counts)))(keys)  # noqa: B023
        assert float(jnp.mean(est.conservative)) <= 1e-3, counts
        ratio = float(jnp.mean(est.variance) / jnp.var(est.mean))
        assert 0.9 <= ratio <= 1.15, (counts, ratio)


def test_a_singularity_above_a_constant_is_still_bounded():
    # 4 + 0.7 x^-0.3 (integral 5): the constant keeps every value within 6-10x the mean on
    # 786432 QMC points, like a bounded f/q, but the singularity skews the replicas' spread
    # as much as without it. Exempting values that reach less than 8x their mean from the
    # power-law test (to spare bounded f/q its false alarms) claimed 6.8e-7 and 1.4e-6 on
    # keys 1 and 3, against errors of 8.2e-6 and 8.5e-6 (12 and 6 sigma): the shape of the
    # tail decides, not its reach.
    f = lambda x: 4.0 + 0.7 * x[0] ** -0.3  # noqa: E731
    for seed in range(4):
        with pytest.warns(jaxmc.ReliabilityWarning, match="upper bound"):
            est = jaxmc.integrate(jax.random.key(seed), f, [0.0], [1.0], n=10**6, method="qmc")
        assert bool(est.conservative), seed
        assert abs(float(est.mean) - 5.0) < 5 * float(est.stderr), seed


def test_a_bounded_ratio_largest_in_a_corner_keeps_the_replicas_error_bar():
    # cos((x0 + ... + x3)/2) through a trained grid: f/q is bounded, largest in the corner
    # x = 1 where the grid's bins are widest, and on 10^5 QMC points its largest values read
    # like a power law (k-hat ~1.2 on the top 128) whose top quarter bends (k-hat ~0.15):
    # a bounded tail. Taking it for a power law swapped the replicas' error bar for an i.i.d.
    # bound some 1000x wider on most keys.
    f = lambda x: jnp.cos(0.5 * jnp.sum(x))  # noqa: E731
    exact = float(jnp.real(((jnp.exp(0.5j) - 1) / 0.5j) ** 4))
    lo, hi = jnp.zeros(4), jnp.ones(4)
    plan = jaxmc.integrate(jax.random.key(0), f, lo, hi, n=10**5, method="grid_qmc").plan
    runs = [jaxmc.integrate(jax.random.key(100 + k), f, lo, hi, n=10**5, method=plan)
            for k in range(32)]
    assert sum(bool(e.conservative) for e in runs) <= 2
    for e in runs:  # each within Student's t at p = 1e-4 (two-sided) of the exact value
        z = abs(float(e.mean) - exact) / float(e.stderr)
        assert sps.t.sf(z, float(e.dof)) > 5e-5, (z, float(e.dof))


def test_a_power_law_in_f_over_q_is_called_only_where_f_has_one():
    # Through a density bounded below, f/q has the tail index of f itself. Values whose
    # largest read as a power law (a generalised Pareto sample, k = 0.4) are called heavy,
    # and still are when f carries that tail times a bounded ratio q; when f is bounded
    # with a smooth maximum (a peak) they are not: the long tail is the density's, bounded.
    rng = np.random.default_rng(0)
    u = rng.uniform(size=10240)
    c = (u**-0.4 - 1) / 0.4 + 1
    assert bool(power_law_tail(tail_of(jnp.asarray(c))))
    ratio = rng.uniform(0.5, 2.0, size=c.shape)
    assert bool(power_law_tail(tail_of(jnp.asarray(c), f=jnp.asarray(c * ratio))))
    peak = np.exp(-rng.uniform(size=c.shape) ** 2 / 0.1)
    assert not bool(power_law_tail(tail_of(jnp.asarray(c), f=jnp.asarray(peak))))


@pytest.mark.filterwarnings("ignore::jaxmc.ReliabilityWarning")
def test_qmc_through_a_grid_keeps_its_error_bar_on_a_bounded_peak():
    # A 2-D Gaussian peak (sigma = 0.02) through the grid `grid_qmc` trains at 2^14: f/q is
    # bounded, but its largest of ~10^4 values rise to 7-28x the median towards the inner
    # edges of the grid's outer bins and read as a power law (k-hat 0.3-0.5): the replicas'
    # error bar was swapped for the i.i.d. bound, 10-30x wider, on 13 of 40 keys. f's own
    # largest values show the bound.
    sigma = 0.02
    f = lambda x: jnp.exp(-jnp.sum((x - 0.5) ** 2) / (2 * sigma**2))  # noqa: E731
    exact = 2 * np.pi * sigma**2 * (1 - 2 * float(sps.norm.sf(0.5 / sigma))) ** 2
    runs = [jaxmc.integrate(jax.random.key(k), f, jnp.zeros(2), jnp.ones(2), n=2**14,
                            method="grid_qmc") for k in range(24)]
    assert not any(bool(e.conservative) for e in runs)
    for e in runs:  # each within Student's t at p = 1e-4 (two-sided) of the exact value
        z = abs(float(e.mean) - exact) / float(e.stderr)
        assert sps.t.sf(z, float(e.dof)) > 5e-5, (z, float(e.dof))


def test_unreliable_under_jit_and_vmap():
    def run(key):
        return jaxmc.uniform(key, lambda x: jnp.where(x < 1e-3, 1.0, 0.0), 0.0, 1.0, 2000)

    keys = jax.random.split(jax.random.key(6), 8)
    flags = jax.jit(jax.vmap(lambda k: stats.unreliable(run(k))))(keys)
    assert flags.shape == (8,) and bool(jnp.all(flags))


def test_float32_error_bar_is_floored_at_the_rounding_error():
    # The case: a mean of ~1000.67 in float32 claimed +-1.1e-7 (an ulp is 6e-5).
    # (The tests run with x64 on: float32 bounds make a float32 run.)
    lo, hi = jnp.zeros(2, jnp.float32), jnp.ones(2, jnp.float32)
    est = jaxmc.integrate(jax.random.key(7), lambda x: jnp.sum(x**2) + 1000.0, lo, hi, n=2**24,
                          method="plain")
    assert est.mean.dtype == jnp.float32
    assert float(est.stderr) >= stats.rounding_floor(jnp.float32) * 1000.0
    assert abs(float(est.mean) - (1000 + 2 / 3)) <= 5 * float(est.stderr)


def test_a_variance_outside_the_dtypes_range_is_flagged():
    # A 4-D Gaussian peak scaled by 1e-14 or 1e25, in float32: the variance of the mean
    # (near 1e-46) flushed to 0, or the values' squares overflowed. Both were returned
    # without a word, the first as 9.86971(0)e-18: an exact mean.
    # (float32 throughout, as by default: the tests run with x64 on, whose float64 sums
    # would hold the small variance.)
    peak = lambda scale: lambda x: scale * jnp.exp(-jnp.sum((x - 0.5) ** 2) / 0.01)
    with jax.enable_x64(False):
        lo, hi = jnp.zeros(4), jnp.ones(4)
        for scale in (1e-14, 1e25):
            with pytest.warns(jaxmc.ReliabilityWarning, match="outside its dtype's range"):
                est = jaxmc.integrate(jax.random.key(0), peak(scale), lo, hi, n=100_000)
            assert est.mean.dtype == jnp.float32 and float(est.mean) != 0
            tiny = float(jnp.finfo(jnp.float32).tiny)
            assert not tiny <= float(est.variance) < np.inf and bool(stats.unreliable(est))
        # Under jit, on the result.
        run = jax.jit(lambda k: jaxmc.integrate(k, peak(1e-20), lo, hi, n=2**16, method="qmc"))
        est = run(jax.random.key(1))
        assert float(est.variance) < tiny and float(est.mean) != 0 and bool(stats.unreliable(est))
        # With a tolerance: never met (a variance of 0 reads as met), and the stream stops
        # (an overflowed sum of squares stays so) rather than run to max_n, 2^30.
        for scale in (1e-20, 1e25):
            with pytest.warns(jaxmc.ReliabilityWarning, match="outside its dtype's range"):
                est = jaxmc.integrate(jax.random.key(2), peak(scale), lo, hi, rtol=1e-2,
                                      method="qmc")
            assert not bool(est.converged) and int(est.n) < 2**20
    # In float64 the same integrands are in range: no warning (warnings are errors here).
    for scale in (1e-14, 1e25):
        est = jaxmc.integrate(jax.random.key(0), peak(scale), jnp.zeros(4), jnp.ones(4),
                              n=100_000)
        assert 0 < float(est.variance) < np.inf and not bool(stats.unreliable(est))


def test_vegas_adapts_in_float32_at_any_magnitude():
    # The same peak scaled by 1e25 or 1e-25: its squares over- or underflowed float32 and the
    # grid refined on zeros where f was largest (errors 14-77% and 2-5%). In units of each
    # round's largest value the grid adapts as unscaled (relative stderr ~2e-3: 5 sigma 1e-2),
    # and the error bar, which float32 cannot hold, is flagged.
    exact = (0.1 * np.sqrt(np.pi)) ** 4  # (erf(5) = 1 - 1.5e-12)
    with jax.enable_x64(False):
        for scale in (1e25, 1e-25):
            f = lambda x, s=scale: s * jnp.exp(-jnp.sum((x - 0.5) ** 2) / 0.01)
            for seed in range(3):
                with pytest.warns(jaxmc.ReliabilityWarning, match="outside its dtype's range"):
                    est = jaxmc.integrate(jax.random.key(seed), f, jnp.zeros(4), jnp.ones(4),
                                          n=100_000, method="adaptive")
                assert abs(float(est.mean) / scale / exact - 1) < 1e-2, (scale, seed)


@pytest.mark.parametrize("method", ["plain", "qmc"])
def test_float32_prod_cos_is_within_5_reported_sigma(method):
    truth = np.sin(1.0) ** 4
    lo, hi = jnp.zeros(4, jnp.float32), jnp.ones(4, jnp.float32)
    est = jaxmc.integrate(jax.random.key(8), lambda x: jnp.prod(jnp.cos(x)), lo, hi, n=2**24,
                          method=method)
    assert est.mean.dtype == jnp.float32
    assert abs(float(est.mean) - truth) <= 5 * float(est.stderr)
    assert float(est.stderr) >= stats.rounding_floor(jnp.float32) * 0.5 * truth


def test_qmc_error_bar_on_an_unbounded_integrand_covers():
    # x^-1/3: finite variance, but 5-9 replica means of a scrambled net are so skewed that
    # their spread covered the truth at 2 sigma in only 30 of 40 keys (down to -5.8 sigma).
    f = lambda x: x[0] ** (-1 / 3)  # noqa: E731
    run = jax.jit(jax.vmap(lambda k: jaxmc.integrate(k, f, jnp.zeros(1), jnp.ones(1), n=2**18,
                                                     method="qmc")))
    est = run(jax.random.split(jax.random.key(9), 40))
    z = (est.mean - 1.5) / est.stderr
    assert np.mean(np.abs(z) <= 2) >= 0.9
    qmc = jaxmc.randomized_qmc(jax.random.key(9), f, [0.0], [1.0], 2**12, replicas=8)
    plain = jaxmc.uniform(jax.random.key(9), f, [0.0], [1.0], 2**15)
    assert float(qmc.variance) >= 0.5 * float(plain.variance)  # the i.i.d. bound applies


def test_adapt_rounds_on_a_thin_shell_are_not_combined_towards_the_low_ones():
    # The indicator of a shell (r = 0.3, w = 0.01) in 3-D: VEGAS+ rounds of 2048 points
    # have skewed f/p, and a round's own variance is small exactly when its estimate is
    # low. Weighted by those, 8 rounds came out 25% low on average over keys (2-sigma
    # coverage 0.27); weighted by the round before (`sequential`), within a few percent.
    r, w = 0.3, 0.01
    exact = 4 / 3 * np.pi * ((r + w) ** 3 - r**3)

    def shell(x):
        s = jnp.sum((x - 0.5) ** 2)
        return jnp.where((s >= r**2) & (s <= (r + w) ** 2), 1.0, 0.0)

    grid = jaxmc.proposals.Grid(jnp.zeros(3), jnp.ones(3))
    keys = jax.random.split(jax.random.key(0), 64)
    est = jax.jit(jax.vmap(
        lambda k: jaxmc.fit.adapt(k, shell, grid, iterations=8, n_per_iteration=2048)[0]
    ))(keys)
    error = np.asarray(est.mean) / exact - 1
    assert abs(np.mean(error)) < 5 * np.std(error) / np.sqrt(len(keys)), np.mean(error)
    z = (np.asarray(est.mean) - exact) / np.asarray(est.stderr)
    assert np.mean(np.abs(z) <= 2) > 0.75, np.mean(np.abs(z) <= 2)

