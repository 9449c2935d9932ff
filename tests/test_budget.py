"""`integrate` spends the budget it is given: whole nets, then extra blocks of every replica."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmc
from benchmarks._harness import normal_equivalent


def _gaussian(x):
    return jnp.exp(-jnp.sum((x - 0.4) ** 2) / 0.1)


def _gaussian_integral(d):
    one = math.sqrt(math.pi * 0.1) / 2 * (math.erf(0.6 / math.sqrt(0.1)) + math.erf(0.4 / math.sqrt(0.1)))
    return one**d


@pytest.mark.parametrize("method", ["auto", "qmc", "stratified", "adaptive", "grid_qmc"])
@pytest.mark.parametrize("n", [2**16, 100_000, 131_071, 300_017])
def test_at_least_95_percent_of_the_budget_is_spent(method, n):
    # Powers of two of points per QMC net left up to a quarter of n unspent (2^16: 77%), and
    # whole stratified blocks of 9^4 points 10% of 2^16.
    est = jaxmc.integrate(jax.random.key(0), _gaussian, jnp.zeros(4), jnp.ones(4), n=n,
                          method=method)
    assert 0.95 * n <= int(est.n) <= n, int(est.n) / n


@pytest.mark.parametrize("f, exact", [
    (_gaussian, _gaussian_integral(2)),
    (lambda x: jnp.where(x[0] + x[1] < 0.8, 1.0, 0.0), 0.32),  # (a kink: QMC's rate is lower)
])
def test_extra_blocks_keep_qmc_unbiased_honest_and_no_worse(f, exact):
    # 131071 = three nets of 2^15 and 10 extra blocks of 2^10 per replica, against the three
    # nets alone (the same keys: the same nets). 400 keys: the mean within 5 standard errors
    # of the closed form, the reported variance the means' (its ratio's sd about 0.09), and
    # the extra blocks' mean squared error no larger than the nets' alone beyond 5 sigma.
    keys = jax.random.split(jax.random.key(0), 400)

    def run(n):
        est = jax.jit(jax.vmap(lambda k: jaxmc.integrate(k, f, jnp.zeros(2), jnp.ones(2), n=n,
                                                         method="qmc")))(keys)
        return est, np.asarray(est.mean) - exact

    nets, nets_error = run(3 * 2**15)
    est, error = run(131_071)
    assert int(est.n[0]) > int(nets.n[0])
    assert abs(np.mean(error)) <= 5 * np.std(error) / np.sqrt(error.size)
    assert 0.6 <= np.mean(np.asarray(est.variance)) / np.var(error) <= 1.5
    z = normal_equivalent(np.abs(error) / np.asarray(est.stderr), np.asarray(est.dof, float))
    assert np.mean(z <= 2) >= 0.9
    gain = error**2 - nets_error**2
    assert np.mean(gain) <= 5 * np.std(gain) / np.sqrt(gain.size)
