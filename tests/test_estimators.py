"""The basic estimator (eq. 8) and importance sampling (eq. 10/12)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmc
from jaxmc.proposals import Uniform

from .helpers import assert_unbiased_and_honest, cos_product, run_keys


class PowerProposal(eqx.Module):
    """p(x) = (k+1) x^k on [0, 1], sampled by inversion: x = u^(1/(k+1))."""

    k: float

    def sample(self, key, n):
        u = jax.random.uniform(key, (n,))
        x = u ** (1 / (self.k + 1))
        return x, self.pdf(x)

    def pdf(self, x):
        return (self.k + 1) * x**self.k


# (f, lo, hi, exact): scalar and d-dimensional, scalar- and vector-valued.
CASES = {
    "1d": (lambda x: jnp.exp(x), 0.0, 2.0, np.exp(2) - 1),
    "3d": (cos_product, jnp.zeros(3), jnp.ones(3), np.sin(1.0) ** 3),
    "2d-vector": (
        lambda x: jnp.stack([x[0] * x[1], x[0] ** 2, 1.0 + 0 * x[0]]),
        jnp.array([0.0, -1.0]),
        jnp.array([1.0, 1.0]),
        np.array([0.0, 2 / 3, 2.0]),
    ),
}


@pytest.mark.parametrize("name", list(CASES))
@pytest.mark.parametrize("use_jit", [False, True])
def test_uniform_analytic(name, use_jit):
    f, lo, hi, exact = CASES[name]
    est_fn = lambda k: jaxmc.uniform(k, f, lo, hi, 20_000)
    est = (jax.jit(est_fn) if use_jit else est_fn)(jax.random.key(1))
    assert np.all(np.abs(est.mean - exact) <= 5 * est.stderr + 1e-12)
    assert est.n == 20_000 and est.n_nonfinite == 0


@pytest.mark.parametrize("name", list(CASES))
def test_uniform_batched_equals_pointwise(name):
    f, lo, hi, _ = CASES[name]
    key = jax.random.key(2)
    a = jaxmc.uniform(key, f, lo, hi, 1000)
    b = jaxmc.uniform(key, jax.vmap(f), lo, hi, 1000, batched=True)
    np.testing.assert_allclose(a.mean, b.mean, rtol=1e-12)
    np.testing.assert_allclose(a.variance, b.variance, rtol=1e-12)


def test_reported_variance_matches_empirical_over_keys():
    f, lo, hi, exact = CASES["3d"]
    ests = run_keys(lambda key: jaxmc.uniform(key, f, lo, hi, 500), 3, k=2000)
    # Var of a sample variance over k keys: relative sd ~ sqrt(2/(k-1)) (kurtosis ~ normal here).
    assert_unbiased_and_honest(ests, exact)


def test_error_decays_as_inverse_square_root():
    f, lo, hi, exact = CASES["1d"]
    ns = [64, 1024, 16384]
    rms = []
    for i, n in enumerate(ns):
        means = run_keys(lambda key: jaxmc.uniform(key, f, lo, hi, n).mean, 10 + i)
        rms.append(np.sqrt(np.mean((np.asarray(means) - exact) ** 2)))
    slope = np.polyfit(np.log(ns), np.log(rms), 1)[0]
    # RMS over 400 keys has ~3.5% relative noise per point; the slope over 2 decades is
    # within ±0.05 of -1/2 at far more than 5 sigma.
    assert abs(slope + 0.5) < 0.05, slope


def test_grad_matches_analytic_derivative():
    # d/da of the estimate of ∫_0^1 exp(a x) dx is the same-sample estimate of ∫ x exp(a x) dx.
    key = jax.random.key(4)
    a = 1.3
    grad = jax.grad(lambda a: jaxmc.uniform(key, lambda x: jnp.exp(a * x), 0.0, 1.0, 10_000).mean)(a)
    direct = jaxmc.uniform(key, lambda x: x * jnp.exp(a * x), 0.0, 1.0, 10_000)
    np.testing.assert_allclose(grad, direct.mean, rtol=1e-12)
    exact = (np.exp(a) * (a - 1) + 1) / a**2
    assert abs(grad - exact) < 5 * direct.stderr


def test_grad_wrt_bounds():
    # d/dhi ∫_lo^hi x^2 dx = hi^2, exactly for the reparameterised estimator with f = x^2?
    # Not exactly: the estimate is (hi-lo) mean f(lo + (hi-lo)u); its derivative is an unbiased
    # estimate of hi^2.
    key = jax.random.key(5)
    g = jax.grad(lambda hi: jaxmc.uniform(key, lambda x: x**2, 0.0, hi, 20_000).mean)(2.0)
    assert abs(g - 4.0) < 0.05


def test_determinism_and_key_types():
    f, lo, hi, _ = CASES["3d"]
    a = jaxmc.uniform(jax.random.key(7), f, lo, hi, 100)
    b = jaxmc.uniform(jax.random.key(7), f, lo, hi, 100)
    c = jaxmc.uniform(jax.random.PRNGKey(7), f, lo, hi, 100)
    d = jaxmc.uniform(jax.random.key(8), f, lo, hi, 100)
    assert a.mean == b.mean and a.variance == b.variance
    assert np.isfinite(c.mean)
    assert a.mean != d.mean


def test_importance_zero_variance_density():
    # p ∝ f: every weight f/p is the integral (§4.1).
    est = jaxmc.importance(jax.random.key(0), lambda x: 3 * x**2, PowerProposal(2.0), 1000)
    np.testing.assert_allclose(est.mean, 1.0, rtol=1e-12)
    np.testing.assert_allclose(est.variance, 0.0, atol=1e-20)


def test_importance_unbiased_and_better_than_uniform():
    f = lambda x: 4 * x**3
    good = jaxmc.importance(jax.random.key(1), f, PowerProposal(2.0), 20_000)
    plain = jaxmc.importance(jax.random.key(1), f, Uniform(0.0, 1.0), 20_000)
    for est in (good, plain):
        assert abs(est.mean - 1.0) < 5 * est.stderr
    assert good.variance < plain.variance / 5


def test_importance_with_uniform_proposal_equals_uniform_estimator_in_expectation():
    f, lo, hi, exact = CASES["2d-vector"]
    est = jaxmc.importance(jax.random.key(6), f, Uniform(lo, hi), 20_000)
    assert np.all(np.abs(est.mean - exact) <= 5 * est.stderr + 1e-12)


def test_importance_grad_wrt_proposal_parameter_is_reparameterised():
    # E_p[f/p] = ∫ f does not depend on k, so the expected gradient is 0. At k = 2 with
    # x = u^(1/3) the per-sample derivative of f/p is -1/3 - ln(u)/3: mean 0, sd 1/3.
    f = lambda x: 3 * x**2
    n = 1000
    g = jax.jit(jax.grad(lambda k: jaxmc.importance(jax.random.key(0), f, PowerProposal(k), n).mean))(2.0)
    u = jax.random.uniform(jax.random.key(0), (n,))
    np.testing.assert_allclose(g, jnp.mean(-1 / 3 - jnp.log(u) / 3), rtol=1e-8)
    assert abs(g) < 5 / 3 / np.sqrt(n)
    means = jax.vmap(lambda key: jaxmc.importance(key, f, PowerProposal(1.0), 100).mean)(
        jax.random.split(jax.random.key(0), 4)
    )
    assert means.shape == (4,)


def test_nonfinite_values_are_counted_not_propagated():
    # f has a non-integrable singularity at 0 that a sample may hit; p = 0 where f != 0 too.
    f = lambda x: jnp.where(x < 0.5, jnp.nan, 1.0)
    with pytest.warns(jaxmc.ReliabilityWarning, match="non-finite integrand values were seen"):
        est = jaxmc.uniform(jax.random.key(0), f, 0.0, 1.0, 1000)
    assert np.isfinite(est.mean)
    assert 400 < est.n_nonfinite < 600
    zero_pdf = PowerProposal(2.0)
    est = jaxmc.importance(jax.random.key(0), lambda x: 1.0 + 0 * x, zero_pdf, 10)
    assert est.n_nonfinite == 0  # p > 0 at every sample drawn


@pytest.mark.parametrize(
    "call, error, match",
    [
        (lambda: jaxmc.uniform(jax.random.key(0), jnp.sin, 1.0, 0.0, 10), ValueError, "lo"),
        (lambda: jaxmc.uniform(jax.random.key(0), jnp.sin, 0.0, 0.0, 10), ValueError, "lo"),
        (lambda: jaxmc.uniform(jax.random.key(0), jnp.sin, 0.0, 1.0, 0), ValueError, "`n`"),
        (lambda: jaxmc.uniform(jax.random.key(0), jnp.sin, 0.0, 1.0, 10.0), TypeError, "`n`"),
        (lambda: jaxmc.uniform(jax.random.key(0), jnp.sin, jnp.zeros(2), jnp.ones(3), 10), ValueError, "shape"),
        (lambda: jaxmc.uniform(jax.random.key(0), jnp.sin, jnp.zeros((2, 2)), jnp.ones((2, 2)), 10), ValueError, "shape"),
        (lambda: jaxmc.uniform(jax.random.key(0), jnp.sin, 0.0, jnp.inf, 10), ValueError, "finite"),
        (lambda: jaxmc.uniform(jax.random.key(0), "sin", 0.0, 1.0, 10), TypeError, "`f`"),
        (lambda: jaxmc.uniform(0, jnp.sin, 0.0, 1.0, 10), TypeError, "`key`"),
        (lambda: jaxmc.uniform(jax.random.split(jax.random.key(0)), jnp.sin, 0.0, 1.0, 10), ValueError, "vmap"),
        (lambda: jaxmc.uniform(jax.random.key(0), jnp.sum, 0.0, 1.0, 10, batched=True), ValueError, "batched"),
        (lambda: jaxmc.importance(jax.random.key(0), jnp.sin, object(), 10), TypeError, "proposal"),
        (lambda: jaxmc.importance(jax.random.key(0), jnp.sin, Uniform(0.0, 1.0), -1), ValueError, "`n`"),
    ],
)
def test_bad_input(call, error, match):
    with pytest.raises(error, match=match):
        call()
