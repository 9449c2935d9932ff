"""Randomised QMC: unbiased and honest for every point set, faster than plain MC, t intervals."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from jaxmc.estimators import QMCEstimate, randomized_qmc, uniform

from .helpers import (
    SMOOTH2,
    SMOOTH2_HI as HI,
    SMOOTH2_LO as LO,
    assert_unbiased_and_honest,
    run_keys,
    smooth2,
    tilted,
    tilted_da,
    tilted_da_integral,
)


K = 200


def iid_points(key, n, d):
    return jax.random.uniform(key, (n, d))


@pytest.mark.parametrize(
    "points", ["sobol", "halton", "lattice", "latin_hypercube", "stratified", iid_points]
)
def test_rqmc_unbiased_and_honest(points):
    est = run_keys(
        lambda k: randomized_qmc(k, smooth2, LO, HI, 64, points=points, replicas=8), 1, k=K
    )
    assert isinstance(est, QMCEstimate) and est.replicas == 8
    assert est.n[0] == 64 * 8
    # Honest: the replica means are i.i.d., so s^2/R is unbiased for the variance.
    assert_unbiased_and_honest(est, SMOOTH2)


def test_rqmc_sobol_beats_plain_mc_and_converges_fast():
    f = lambda x: smooth2(x)[0]
    errors = []
    for n in (64, 1024):
        est = run_keys(lambda k: randomized_qmc(k, f, LO, HI, n, replicas=4), 2, k=64)
        errors.append(np.sqrt(np.mean((np.asarray(est.mean) - SMOOTH2[0]) ** 2)))
    plain = run_keys(lambda k: uniform(k, f, LO, HI, 1024 * 4), 3, k=64)
    plain_rmse = np.sqrt(np.mean((np.asarray(plain.mean) - SMOOTH2[0]) ** 2))
    slope = np.log(errors[1] / errors[0]) / np.log(16)
    assert slope < -1.0, slope  # scrambled Sobol': ~n^-1.5 for smooth f; plain MC n^-0.5
    assert errors[1] < plain_rmse / 30, (errors, plain_rmse)


def test_scalar_bounds_and_one_replica(key):
    est = jax.jit(lambda k: randomized_qmc(k, jnp.sin, 0.0, 1.0, 128))(key)
    assert abs(est.mean - (1 - np.cos(1))) < 5 * est.stderr
    one = randomized_qmc(key, jnp.sin, 0.0, 1.0, 128, replicas=1)
    assert np.isinf(one.variance)
    low, high = one.t_interval()
    assert np.isneginf(low) and np.isposinf(high)


def test_t_interval_width_and_coverage():
    f = lambda x: smooth2(x)[1]
    est = run_keys(lambda k: randomized_qmc(k, f, LO, HI, 32, replicas=4), 4, k=400)
    low, high = est.t_interval(0.9)
    half = (np.asarray(high) - np.asarray(low)) / 2
    np.testing.assert_allclose(half, stats.t.ppf(0.95, 3) * np.asarray(est.stderr), rtol=1e-9)
    covered = np.mean((np.asarray(low) <= SMOOTH2[1]) & (SMOOTH2[1] <= np.asarray(high)))
    # Binomial band, 5 sigma: a normal interval with 3 dof of variance would cover ~0.80.
    assert abs(covered - 0.9) < 5 * np.sqrt(0.9 * 0.1 / 400), covered


def test_agrees_with_scipy_qmc_quad():
    integrate = pytest.importorskip("scipy.integrate")
    f = lambda x: smooth2(x)[0]
    ours = jax.jit(lambda k: randomized_qmc(k, f, LO, HI, 1024, replicas=8))(jax.random.key(5))
    ref = integrate.qmc_quad(
        lambda x: np.exp(x[0] - x[1]), [0, 0], [1, 2], n_estimates=8, n_points=1024,
        qrng=stats.qmc.Sobol(d=2, rng=np.random.default_rng(5)),
    )
    assert abs(ref.integral - SMOOTH2[0]) < 5 * ref.standard_error
    assert abs(ours.mean - SMOOTH2[0]) < 5 * ours.stderr


def test_jit_vmap_grad(key):
    est = lambda a, k: randomized_qmc(k, tilted(a), LO, HI, 256, replicas=4)
    a = 0.7
    jitted = jax.jit(est)(a, key)
    batch = jax.jit(jax.vmap(est, (0, None)))(jnp.array([0.2, a]), key)
    np.testing.assert_allclose(batch.mean[1], jitted.mean, rtol=1e-12)
    grad = jax.jit(jax.grad(lambda a: est(a, key).mean))(a)
    same_points = jax.jit(lambda k: randomized_qmc(k, tilted_da(a), LO, HI, 256, replicas=4))(key)
    np.testing.assert_allclose(grad, same_points.mean, rtol=1e-10)
    assert abs(grad - tilted_da_integral(a)) < 5 * same_points.stderr


def test_bad_inputs(key):
    with pytest.raises(ValueError, match="points"):
        randomized_qmc(key, smooth2, LO, HI, 64, points="niederreiter")
    with pytest.raises(ValueError, match="`n` must be a perfect"):
        randomized_qmc(key, smooth2, LO, HI, 50, points="stratified")
    with pytest.raises(ValueError, match="points"):
        randomized_qmc(key, smooth2, LO, HI, 64, points=lambda k, n, d: jnp.zeros((n, d + 1)))
    with pytest.raises(ValueError, match="replicas"):
        randomized_qmc(key, smooth2, LO, HI, 64, replicas=0)
    with pytest.raises(TypeError, match="`n`"):
        randomized_qmc(key, smooth2, LO, HI, 64.0)
    with pytest.raises(ValueError, match="level"):
        randomized_qmc(key, smooth2, LO, HI, 64).t_interval(1.5)
