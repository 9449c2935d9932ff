"""The streaming driver `integrate`."""

import math
import os
import subprocess
import sys
import textwrap
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmc

from .helpers import assert_unbiased_and_honest, cos_product, run_keys, subprocess_xla_flags


LO, HI = jnp.zeros(3), jnp.ones(3)
F = lambda x: jnp.sum(x**2)  # ∫ over [0,1]^3 = 1
EXACT = 1.0


def test_tolerance_is_met_and_estimate_is_right():
    est = jaxmc.integrate(jax.random.key(0), F, LO, HI, rtol=2e-3, method="plain")
    assert est.stderr <= 2e-3 * abs(est.mean)
    assert abs(est.mean - EXACT) < 5 * est.stderr
    # It stopped early: far fewer evaluations than the default budget.
    assert est.n < 2**22


def test_tolerance_checks_start_small_whatever_the_chunk():
    # With a tolerance QMC's eight nets are checked from 2^10 points each, and the first chunk
    # is walked in small steps: at the default max_n (2^30) the first check once came after
    # a whole chunk, 2^18 evaluations. The run stops when two checks in a row pass; they fall
    # at the same nets for any chunk.
    from jaxmc._stream._sizes import QMC_PASSES_TO_STOP

    assert QMC_PASSES_TO_STOP == 2
    f = lambda x: jnp.exp(-jnp.sum(x**2))
    exact = (np.sqrt(np.pi) / 2 * math.erf(1.0)) ** 3
    runs = [jaxmc.integrate(jax.random.key(0), f, LO, HI, rtol=rtol, method="qmc", chunk=chunk)
            for rtol in (1e-4, 1e-7) for chunk in (2**13, 2**18)]
    for est in runs:
        assert est.converged and abs(float(est.mean) - exact) < 5 * float(est.stderr)
    assert int(runs[0].n) == 8 * 2**11  # met on the first nets, and on the second
    # ...at 2^14 and 2^15 points: with the default chunk, the last two checks of its small
    # steps (which the first whole step's check repeats, and stops on).
    assert int(runs[2].n) == 8 * 2**15
    for small, large in (runs[:2], runs[2:]):
        assert int(small.n) == int(large.n)
        np.testing.assert_allclose(small.mean, large.mean, rtol=1e-12)


def test_block_means_meet_a_tolerance_from_sixteen_blocks_on():
    # Stratified blocks (25^3 points in 3-D) are units of one degree of freedom each: a loose
    # tolerance stops the run at the sixteenth, not at the second nor after a whole chunk.
    from jaxmc._stream._sizes import MIN_BLOCKS_TO_STOP

    assert MIN_BLOCKS_TO_STOP == 16
    est = jaxmc.integrate(jax.random.key(1), F, LO, HI, rtol=0.5, method="stratified")
    assert est.converged and int(est.n) == 16 * 25**3


def test_atol_and_budget_cap():
    # An unreachable tolerance stops at the budget, says so on the result and warns.
    with pytest.warns(jaxmc.ReliabilityWarning, match="tolerance was not met"):
        est = jaxmc.integrate(jax.random.key(1), F, LO, HI, atol=1e-9, max_n=50_000, method="plain")
    assert est.n == 50_000 and not est.converged
    assert abs(est.mean - EXACT) < 5 * est.stderr
    est = jaxmc.integrate(jax.random.key(1), F, LO, HI, atol=1e-2, max_n=50_000, method="plain")
    assert est.converged and est.stderr <= 1e-2 and est.method == "plain" and est.pilot is None


def test_fixed_n_counts_exactly_and_vector_valued():
    f = lambda x: jnp.stack([x, x**2, jnp.sin(x)])
    est = jaxmc.integrate(jax.random.key(2), f, 0.0, 1.0, n=30_001, method="plain")
    assert est.n == 30_001 and est.mean.shape == (3,)
    exact = np.array([0.5, 1 / 3, 1 - np.cos(1.0)])
    assert np.all(np.abs(est.mean - exact) < 5 * est.stderr)


@pytest.mark.parametrize("method", ["plain", "qmc", "stratified", "adaptive"])
def test_chunk_invariance_and_determinism(method):
    key = jax.random.key(3)
    # A discontinuous integrand, so that no method is exact to rounding.
    g = lambda x: jnp.exp(jnp.sum(x)) * (x[0] < 0.37)
    runs = [
        jaxmc.integrate(key, g, LO, HI, n=200_000, method=method, chunk=chunk)
        for chunk in (1, 2**15, 2**20)
    ]
    for est in runs[1:]:
        np.testing.assert_allclose(est.mean, runs[0].mean, rtol=1e-12)
        np.testing.assert_allclose(est.variance, runs[0].variance, rtol=1e-9)
        assert est.n == runs[0].n
    again = jaxmc.integrate(key, g, LO, HI, n=200_000, method=method, chunk=2**15)
    assert again.mean == runs[1].mean


def test_reported_variance_honest_over_keys():
    ests = run_keys(lambda k: jaxmc.integrate(k, F, LO, HI, n=2000, method="plain"), 4, k=500)
    assert_unbiased_and_honest(ests, EXACT)


@pytest.mark.parametrize("method", ["qmc", "stratified"])
def test_block_methods_unbiased_honest_and_better_than_plain(method):
    # Each block is one independent randomisation; the variance comes from block means.
    exact = np.sin(1.0) ** 3
    run = lambda m: run_keys(
        lambda k: jaxmc.integrate(k, cos_product, LO, HI, n=2**12, method=m), 9, k=200
    )
    ests, plain = run(method), run("plain")
    means = np.asarray(ests.mean)
    z = (means - exact) / np.sqrt(np.asarray(ests.variance))
    assert abs(np.mean(means - exact)) < 5 * np.std(means) / np.sqrt(200)
    # 8 blocks: the t-like z has sd sqrt(7/5) ≈ 1.18; an optimistic variance would inflate it.
    assert 0.8 < np.std(z) < 1.6
    assert np.var(means) < np.var(np.asarray(plain.mean)) / 4


def test_qmc_error_bar_has_its_replicas_degrees_of_freedom():
    # 5 * 512 evaluations: five nets of 512, so 4 degrees of freedom, and `interval` is
    # Student's t; it covers at its level, where mean +- 1.96 stderr would cover ~0.88.
    exact = np.sin(1.0) ** 3
    ests = run_keys(lambda k: jaxmc.integrate(k, cos_product, LO, HI, n=5 * 512, method="qmc"),
                    10, k=400)
    assert np.all(np.asarray(ests.dof) == 4)
    low, high = ests.interval(0.95)
    covered = np.mean((np.asarray(low) <= exact) & (exact <= np.asarray(high)))
    assert abs(covered - 0.95) < 5 * np.sqrt(0.95 * 0.05 / 400), covered


def test_qmc_has_no_bias_from_its_32_bit_points():
    # Genz's 2-D corner peak on 3 nets of 2^18: the nets' spread is often 1e-11 to 1e-10
    # relative, below the 4e-10 that points at the left ends of their 2^-32 cells would
    # shift every replica by alike (a common bias the spread cannot see: the t interval
    # then covered 0.6-0.7).
    a = 1.85 / 2
    exact = (1.0 - 2.0 / (1.0 + a) + 1.0 / (1.0 + 2.0 * a)) / (2.0 * a * a)
    f = lambda x: (1.0 + a * jnp.sum(x)) ** -3
    lo, hi = jnp.zeros(2), jnp.ones(2)
    ests = run_keys(lambda k: jaxmc.integrate(k, f, lo, hi, n=3 * 2**18, method="qmc"), 12, k=40)
    assert np.all(np.asarray(ests.dof) == 2)
    low, high = ests.interval(0.954)
    covered = np.mean((np.asarray(low) <= exact) & (exact <= np.asarray(high)))
    # At the nominal 0.954, 40 keys cover less than 0.8 with probability 7e-5.
    assert covered >= 0.8, covered


def test_grad_with_fixed_budget():
    key = jax.random.key(5)
    g = jax.grad(lambda a: jaxmc.integrate(key, lambda x: jnp.exp(a * x), 0.0, 1.0, n=50_000, method="plain").mean)(1.0)
    exact = 1.0  # d/da (e^a - 1)/a at a = 1 is (e(a - 1) + 1)/a^2 = 1
    assert abs(g - exact) < 0.02


def test_jit_inside_user_pipeline():
    @jax.jit
    def pipeline(key, scale):
        return jaxmc.integrate(key, lambda x: scale * F(x), LO, HI, n=10_000, method="plain").mean

    assert abs(pipeline(jax.random.key(6), 2.0) - 2.0) < 0.05


def test_nonfinite_raises_or_drops():
    f = lambda x: jnp.where(x < 0.01, jnp.inf, 1.0)
    with pytest.raises(FloatingPointError, match="nonfinite='drop'"):
        jaxmc.integrate(jax.random.key(7), f, 0.0, 1.0, n=10_000, method="plain")
    with warnings.catch_warnings():
        warnings.simplefilter("error", jaxmc.ReliabilityWarning)  # (dropped on request: no news)
        est = jaxmc.integrate(jax.random.key(7), f, 0.0, 1.0, n=10_000, method="plain",
                              nonfinite="drop")
    assert 50 < est.n_nonfinite < 150 and np.isfinite(est.mean)
    # One verdict: no warning, and the flags agree, eagerly and under jit.
    assert not bool(jaxmc.stats.unreliable(est)) and not jaxmc.stats.reliability_reasons(est)
    traced = jax.jit(lambda k: jaxmc.stats.unreliable(jaxmc.integrate(
        k, f, 0.0, 1.0, n=10_000, method="plain", nonfinite="drop")))(jax.random.key(7))
    assert not bool(traced)


def test_progress_reports(capfd):
    jaxmc.integrate(jax.random.key(8), F, LO, HI, n=100_000, method="plain", chunk=2**15, progress=True)
    err = capfd.readouterr().err
    # A tqdm bar on stderr, at 100% of the budget, closed with a newline.
    assert "100k/100k" in err and err.endswith("\n")


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        ({}, ValueError, "budget"),
        ({"n": 10, "max_n": 10}, ValueError, "max_n"),
        ({"rtol": -1.0}, ValueError, "rtol"),
        ({"atol": float("nan")}, ValueError, "atol"),
        ({"n": 0}, ValueError, "`n`"),
        ({"n": 2**31}, ValueError, "budget"),
        ({"n": 10, "method": "magic"}, ValueError, "method"),
        ({"n": 10, "nonfinite": "ignore"}, ValueError, "nonfinite"),
        ({"n": 10, "mesh": "cpu"}, TypeError, "mesh"),
        ({"n": 10, "chunk": 0}, ValueError, "chunk"),
        # (the default method's own minimum, not that of the QMC it runs on such budgets)
        ({"n": 10}, ValueError, r"`n` must be >= 16 for method 'auto'"),
        ({"rtol": 0.1, "max_n": 10}, ValueError, r"`max_n` must be >= 16 for method 'auto'"),
    ],
)
def test_bad_input(kwargs, error, match):
    with pytest.raises(error, match=match):
        jaxmc.integrate(jax.random.key(0), F, LO, HI, **kwargs)


def test_bad_bounds():
    with pytest.raises(ValueError, match="lo"):
        jaxmc.integrate(jax.random.key(0), F, HI, LO, n=10)


def _run_script(code: str, env_extra: dict[str, str]) -> str:
    env = {**os.environ, **env_extra}
    out = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, env=env, timeout=600
    )
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_four_devices_match_one_device():
    code = """
        import jax, jax.numpy as jnp, jaxmc
        jax.config.update("jax_enable_x64", True)
        assert len(jax.devices()) == 4, jax.devices()
        f = lambda x: jnp.stack([jnp.sum(x**2), jnp.prod(jnp.cos(x))])
        key = jax.random.key(11)
        one = jax.make_mesh((1,), ("b",), devices=jax.devices()[:1],
                            axis_types=(jax.sharding.AxisType.Auto,))
        a = jaxmc.integrate(key, f, jnp.zeros(3), jnp.ones(3), n=300_000, method="plain", chunk=2**15)
        b = jaxmc.integrate(key, f, jnp.zeros(3), jnp.ones(3), n=300_000, method="plain", mesh=one)
        t = jaxmc.integrate(key, f, jnp.zeros(3), jnp.ones(3), rtol=1e-3, method="plain")
        c = jaxmc.integrate(key, f, jnp.zeros(3), jnp.ones(3), n=300_000, method="adaptive",
                            chunk=2**15)
        e = jaxmc.integrate(key, f, jnp.zeros(3), jnp.ones(3), n=300_000, method="adaptive",
                            mesh=one)
        # QMC to a tolerance: its first chunk in small steps, a round of 8 blocks each
        q = jaxmc.integrate(key, f, jnp.zeros(3), jnp.ones(3), rtol=1e-7, method="qmc")
        r = jaxmc.integrate(key, f, jnp.zeros(3), jnp.ones(3), rtol=1e-7, method="qmc", mesh=one)
        print(*a.mean.tolist(), *b.mean.tolist(), *a.variance.tolist(), *b.variance.tolist(),
              int(a.n), int(b.n), float(t.stderr[0] / t.mean[0]),
              *c.mean.tolist(), *e.mean.tolist(), *c.variance.tolist(), *e.variance.tolist(),
              *q.mean.tolist(), *r.mean.tolist(), int(q.n), int(r.n))
    """
    values = _run_script(code, {"XLA_FLAGS": subprocess_xla_flags(devices=4)}).split()
    a_mean, b_mean = np.array(values[0:2], float), np.array(values[2:4], float)
    a_var, b_var = np.array(values[4:6], float), np.array(values[6:8], float)
    np.testing.assert_allclose(a_mean, b_mean, rtol=1e-12)
    np.testing.assert_allclose(a_var, b_var, rtol=1e-9)
    assert values[8] == values[9] == "300000"
    assert float(values[10]) <= 1e-3
    adaptive = np.array(values[11:19], float).reshape(4, 2)  # means and variances, 4 and 1 devices
    np.testing.assert_allclose(adaptive[0], adaptive[1], rtol=1e-12)
    np.testing.assert_allclose(adaptive[2], adaptive[3], rtol=1e-9)
    qmc = np.array(values[19:23], float).reshape(2, 2)  # means, 4 and 1 devices
    np.testing.assert_allclose(qmc[0], qmc[1], rtol=1e-12)
    assert values[23] == values[24] and 8 * 2**10 < int(values[23]) < 2**20


@pytest.mark.slow
@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="needs Linux /proc")
def test_billion_float32_samples_bounded_memory_and_accurate():
    # 10^9 float32 samples of x on [0,1]: a naive float32 running sum would stall at 2^24;
    # merged per-block moments keep the mean within a few stderr (≈ 9e-6) of 1/2.
    code = """
        import jax, jaxmc
        est = jaxmc.integrate(jax.random.key(0), lambda x: x, 0.0, 1.0, n=10**9, method="plain",
                              chunk=2**21)
        # VmHWM is this process's peak resident memory since exec; getrusage's ru_maxrss
        # would also carry the (large) peak of the pytest worker that forked it.
        status = open("/proc/self/status").read().split("VmHWM:")[1].split()
        rss = int(status[0]) * 1024
        print(float(est.mean), float(est.stderr), int(est.n), rss, est.mean.dtype)
    """
    # (At XLA's level 1: unoptimised, as the other tests compile, this run takes 77 s, not 17.)
    flags = {"XLA_FLAGS": "--xla_backend_optimization_level=1"}
    mean, stderr, n, rss, dtype = _run_script(code, flags).split()
    assert dtype == "float32" and int(n) == 10**9
    assert abs(float(mean) - 0.5) < 5 * float(stderr)
    np.testing.assert_allclose(float(stderr), np.sqrt(1 / 12 / 1e9), rtol=1e-3)
    assert int(rss) < 2**30


def test_adaptive_method_fits_a_grid_and_stays_unbiased():
    # A narrow 4-D Gaussian peak: plain MC barely sees it, the trained VEGAS+ grid does.
    width = 0.02
    f = lambda x: jnp.exp(-jnp.sum((x - 0.5) ** 2) / (2 * width**2))
    exact = (2 * np.pi * width**2) ** 2  # the tails beyond the box are < 1e-100
    key = jax.random.key(12)
    adaptive = jaxmc.integrate(key, f, jnp.zeros(4), jnp.ones(4), n=400_000, method="adaptive")
    with pytest.warns(jaxmc.ReliabilityWarning, match="Pareto"):  # a peak sampled too sparsely
        plain = jaxmc.integrate(key, f, jnp.zeros(4), jnp.ones(4), n=400_000, method="plain")
    # Whole VEGAS+ rounds of 2^14 points: the budget is rounded down to a multiple.
    assert 400_000 - 2**14 < adaptive.n <= 400_000
    assert abs(adaptive.mean - exact) < 5 * adaptive.stderr
    assert adaptive.stderr < plain.stderr / 50
    with pytest.raises(ValueError, match="adaptive"):
        jaxmc.integrate(key, f, jnp.zeros(4), jnp.ones(4), n=1000, method="adaptive")


def test_adaptive_rounds_keep_adapting_after_training():
    """The 10-D ball of radius 0.45 (0.09% of the cube) at 1e5 evaluations: a grid frozen
    after its training rounds left a relative error of 0.18-0.25 (plain Monte Carlo: 0.11,
    vegas: 0.024); rounds that keep refining it, combined, measured 0.008 over 32 keys."""
    d, r = 10, 0.45
    f = lambda x: (jnp.sum((x - 0.5) ** 2) <= r**2).astype(x.dtype)
    exact = np.pi ** (d / 2) / math.gamma(d / 2 + 1) * r**d
    est = run_keys(lambda k: jaxmc.integrate(k, f, jnp.zeros(d), jnp.ones(d), n=100_000,
                                             method="adaptive"), 6, k=8)
    relerr = np.asarray(est.mean) / exact - 1
    assert np.sqrt(np.mean(relerr**2)) < 0.03, relerr
    assert np.mean(np.abs(relerr) < 3 * np.asarray(est.stderr) / exact) >= 0.75


def test_adaptive_rounds_on_a_thin_shell_are_not_weighted_towards_the_low_ones():
    """Rounds of 256 points on a thin 3-D shell starve it and come out low with small
    variances; weighting them by (predicted) inverse variances left every run low and
    unflagged two times in three. Rounds weighted in advance keep the misses flagged."""
    r, w = 0.3, 0.01
    f = lambda x: (jnp.abs(jnp.sqrt(jnp.sum((x - 0.5) ** 2)) - r) <= w / 2).astype(x.dtype)
    exact = 4 / 3 * np.pi * ((r + w / 2) ** 3 - (r - w / 2) ** 3)
    est = run_keys(lambda k: jaxmc.integrate(k, f, jnp.zeros(3), jnp.ones(3), n=2**14,
                                             method="adaptive"), 7, k=64)
    missed = np.abs(np.asarray(est.mean) - exact) > 2 * np.asarray(est.stderr)
    flagged = np.asarray(jaxmc.stats.unreliable(est))
    assert np.mean(missed & ~flagged) <= 0.2, (np.mean(missed), np.mean(flagged))


def _posterior(d=5, width=0.02, rho=0.7):
    """A correlated Gaussian likelihood on [0,1]^d (all its mass inside) and its integral."""
    cov = width**2 * rho ** np.abs(np.subtract.outer(np.arange(d), np.arange(d)))
    prec, mu = jnp.asarray(np.linalg.inv(cov)), jnp.asarray(np.linspace(0.4, 0.6, d))
    f = lambda x: jnp.exp(-0.5 * (x - mu) @ prec @ (x - mu))
    return f, float(np.sqrt((2 * np.pi) ** d * np.linalg.det(cov)))


def test_adaptive_reaches_a_tolerance_on_a_narrow_posterior():
    """vegas needs about 2e6 evaluations (10 x 1e5 to train, 10 x 1e5 to measure) for a
    relative error of 1e-3 here; the adaptive method (VEGAS+ rounds on the frozen grid and
    allocation) stays within 5x of that, and its error bar is honest."""
    f, exact = _posterior()
    lo, hi = jnp.zeros(5), jnp.ones(5)
    # A separable grid on a correlated 5-D peak keeps ess/n near 0.07 and k-hat near the
    # 0.7 gate (0.5-0.77 over keys, with or without the grid's defensive share), so the
    # tail warning may fire; the error bar itself is checked against the truth below.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", jaxmc.ReliabilityWarning)
        est = jaxmc.integrate(jax.random.key(3), f, lo, hi, rtol=1e-3, method="adaptive")
        loose = jaxmc.integrate(jax.random.key(3), f, lo, hi, rtol=2e-2, method="adaptive")
    assert float(est.stderr) <= 1e-3 * abs(float(est.mean))
    assert int(est.n) <= 1e7
    assert abs(float(est.mean) - exact) < 4 * float(est.stderr)
    # With only rtol the grid first trains as for 2^17 evaluations (ten rounds of 2^11): at
    # 1e-3 that probe asked for more than twice 2^17 and the grid trained anew on rounds of
    # 2^14 (the probe's 10 * 2^11 counted in n); at 2e-2 sixteen refining rounds of the
    # probe's grid met it (training for max_n took 0.43M evaluations at any rtol).
    assert (int(est.n) - 10 * 2**11) % 2**14 == 0, int(est.n)
    assert int(loose.n) == 10 * 2**11 + 16 * 2**11
    assert float(loose.stderr) <= 2e-2 * abs(float(loose.mean))
    assert abs(float(loose.mean) - exact) < 5 * float(loose.stderr)


def test_adaptive_method_is_unbiased_and_honest_over_keys():
    """Training and measuring use independent randomness: over keys the estimates centre on
    the integral and scatter as their reported variances say."""
    f, exact = _posterior(d=3, width=0.05)
    lo, hi = jnp.zeros(3), jnp.ones(3)
    est = run_keys(lambda k: jaxmc.integrate(k, f, lo, hi, n=2**17, method="adaptive"), 5, k=64)
    assert_unbiased_and_honest(est, exact)
