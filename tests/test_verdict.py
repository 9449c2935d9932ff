"""One verdict: `converged`, `unreliable` and the warnings agree."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmc
from jaxmc.stats import ReliabilityWarning, reliability_reasons, unreliable


ZEROS, ONES = jnp.zeros(4, jnp.float32), jnp.ones(4, jnp.float32)


def test_a_tolerance_met_on_no_non_zero_value_is_not_converged():
    # A 4-D spike of width 0.002 no sample hits: the values are all 0, their spread 0, which
    # "meets" any tolerance. In float32, JAX's default (the tests run in float64, where a grid
    # finds it).
    spike = lambda x: jnp.exp(-jnp.sum((x - 0.5) ** 2) / (2 * 0.002**2))  # noqa: E731
    with pytest.warns(ReliabilityWarning, match="non-zero"):
        est = jaxmc.integrate(jax.random.key(0), spike, ZEROS, ONES, rtol=1e-2)
    assert est.mean.dtype == jnp.float32 and int(est.n_nonzero) == 0
    assert not bool(est.converged) and bool(unreliable(est))
    # Under jit: the same verdict, on the result.
    run = jax.jit(lambda k: jaxmc.integrate(k, spike, ZEROS, ONES, rtol=1e-2))
    assert not bool(run(jax.random.key(0)).converged)


def test_a_met_tolerance_on_a_trusted_error_bar_converges():
    f = lambda x: jnp.exp(-jnp.sum(x**2))  # noqa: E731
    est = jaxmc.integrate(jax.random.key(0), f, jnp.zeros(2), jnp.ones(2), rtol=1e-3)
    assert bool(est.converged) and not bool(unreliable(est))


def test_an_expectation_is_unreliable_where_its_evidence_is():
    # An evidence of about 2e-21: its variance (~1e-45) is below float32's smallest normal
    # number, 0 or subnormal, while the ratio's is fine.
    log_density = lambda x: -0.5 * jnp.sum(((x - 0.3) / 0.1) ** 2) - 45.0  # noqa: E731
    with pytest.warns(ReliabilityWarning, match="evidence"):
        est = jaxmc.expectation(jax.random.key(0), lambda x: x, log_density,
                                -jnp.ones(2, jnp.float32), jnp.ones(2, jnp.float32), n=20_000)
    assert est.mean.dtype == jnp.float32 and bool(unreliable(est.norm))
    assert bool(unreliable(est))
    assert any("evidence" in reason for reason in reliability_reasons(est))
    # Its logarithm is representable, and trusted.
    assert not bool(unreliable(est.log_norm))


def test_an_evidence_bounded_conservatively_says_so_and_leaves_the_mean_alone():
    # A correlated Gaussian posterior on the plane: on some keys the grid's weights read a
    # power-law tail and the evidence's error bar is their i.i.d. bound, several times the
    # spread of the estimates. Those keys' evidence says it is an upper bound; the posterior
    # mean, whose error bar is its own, is not flagged for it.
    cov = jnp.array([[0.25, 0.9], [0.9, 4.0]])
    mu, precision = jnp.array([0.7, -1.3]), jnp.linalg.inv(cov)
    log_density = lambda x: -0.5 * (x - mu) @ precision @ (x - mu)  # noqa: E731
    ests = [jaxmc.expectation(jax.random.key(seed), lambda x: x, log_density, [-jnp.inf] * 2,
                              [jnp.inf] * 2, n=10**5) for seed in range(6)]
    stderr = np.array([float(e.log_norm.stderr) for e in ests])
    bounded = np.array([bool(e.log_norm.conservative) and bool(e.norm.conservative) for e in ests])
    assert np.any(stderr > 3 * stderr.min())  # (the case this test is about)
    assert np.all(bounded == (stderr > 3 * stderr.min())), (stderr, bounded)
    assert all(bool(unreliable(e.norm)) == b for e, b in zip(ests, bounded))
    assert not any(bool(unreliable(e)) for e in ests)
    log_z = np.log(2 * np.pi * np.sqrt(np.linalg.det(np.asarray(cov))))
    assert all(abs(float(e.log_norm.mean) - log_z) < 4 * float(e.log_norm.stderr) for e in ests)
