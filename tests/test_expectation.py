"""`expectation`: moments and evidence of an unnormalised posterior, with honest error bars.

The posterior is a correlated 3-D Gaussian well inside the unit cube (at least
six standard deviations from every face, so the truncation changes the moments
by less than 1e-8), whose mean, covariance and integral are known in closed form.
Everything runs through one log density that takes its offset as `args`, so
the compiled code is shared between the tests.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmc

from .helpers import compilations


D = 3
LO, HI = jnp.zeros(D), jnp.ones(D)
MU = jnp.array([0.45, 0.5, 0.55])
SD = jnp.array([0.06, 0.08, 0.05])
CORR = jnp.array([[1.0, 0.6, -0.3], [0.6, 1.0, 0.4], [-0.3, 0.4, 1.0]])
COV = CORR * SD[:, None] * SD[None, :]
PRECISION = jnp.linalg.inv(COV)
N = 8192
KEYS = 64


def log_posterior(x, offset):
    r = x - MU
    return -0.5 * r @ PRECISION @ r + offset


def moments(x, offset):
    """The point and its centred outer product, `(D + 1, D)`: E is (MU, COV)."""
    return jnp.concatenate([x[None], jnp.outer(x - MU, x - MU)])


TRUTH = np.concatenate([np.asarray(MU)[None], np.asarray(COV)])


def log_evidence(offset):
    return offset + 0.5 * float(jnp.linalg.slogdet(2 * jnp.pi * COV)[1])


def distinct(a):
    """The distinct components of a `(..., D + 1, D)` array: the mean and the covariance's upper triangle."""
    rows, cols = np.triu_indices(D)
    return jnp.concatenate([a[..., 0, :], a[..., 1 + rows, cols]], axis=-1)


@pytest.fixture(scope="module")
def many_keys():
    """Each method on 64 keys at a log density of -1000, stacked: the grid in float32 (the
    default dtype), the mixture in float64. Eagerly, one key at a time: the code compiled for
    the first key (and shared with the other tests) serves them all."""
    keys = jax.random.split(jax.random.key(20261122), KEYS)
    runs = {}
    # (A Python float offset, as the other tests pass: a typed float64 one would compile anew.)
    for method, dtype, offset in (("grid", jnp.float32, jnp.float32(-1000.0)),
                                  ("mixture", jnp.float64, -1000.0)):
        lo, hi = LO.astype(dtype), HI.astype(dtype)
        ests = [jaxmc.expectation(k, moments, log_posterior, lo, hi, n=N, method=method, args=offset)
                for k in keys]
        runs[method] = jax.tree.map(lambda *a: np.stack(a), *ests)
    return runs


def assert_honest(z, name):
    """z-scores `(keys, components)` against a standard normal: all within 5 sigma, the mean
    of z^2 within 5 standard errors of 1 (the standard error from the spread of the per-key
    means, since the components of one key are correlated), and the share within 2 sigma
    within 5 binomial standard errors of 95.45%."""
    z = np.asarray(z)
    assert np.all(np.abs(z) < 5), f"{name}: max |z| = {np.max(np.abs(z)):.2f}"
    per_key = np.mean(z**2, axis=1)
    t = (per_key.mean() - 1) / (per_key.std(ddof=1) / math.sqrt(len(per_key)))
    assert abs(t) < 5, f"{name}: mean z^2 = {per_key.mean():.3f} ({t:.1f} standard errors from 1)"
    p = 0.9545
    within = np.mean(np.abs(z) < 2)
    assert abs(within - p) < 5 * math.sqrt(p * (1 - p) / len(z)), f"{name}: {within:.3f} within 2 sigma"


@pytest.mark.parametrize("method", ["grid", "mixture"])
def test_moments_are_within_their_error_bars_over_many_keys(many_keys, method):
    est = many_keys[method]
    assert est.mean.shape == (KEYS, D + 1, D)
    assert est.mean.dtype == {"grid": np.float32, "mixture": np.float64}[method]
    assert np.all(np.asarray(est.n) == N)
    assert np.all(np.asarray(est.n_nonfinite) == 0)
    assert_honest(distinct((est.mean - TRUTH) / est.stderr), method)


def test_the_mixture_reports_an_honest_log_evidence(many_keys):
    est = many_keys["mixture"].log_norm
    z = (est.mean - log_evidence(-1000.0)) / est.stderr
    assert_honest(z[:, None], "log evidence")


def test_the_grid_log_evidence_is_right_and_conservative(many_keys):
    # The grid's weights have a power-law tail (Pareto k above 0.2) on a correlated
    # posterior, where jaxmc bounds a stratified variance by the i.i.d. one: wide, not narrow.
    # (In float32, log Z ~ -1008 is rounded to ~6e-5, far below its error bar.)
    est = many_keys["grid"].log_norm
    z = np.asarray((est.mean - log_evidence(-1000.0)) / est.stderr)
    assert np.all(np.abs(z) < 5)
    assert np.mean(z**2) < 1 + 5 * math.sqrt(2 / KEYS)


@pytest.mark.parametrize("method", ["grid", "mixture"])
def test_a_log_density_of_minus_1000_keeps_its_evidence_in_log_norm(many_keys, method):
    est = many_keys[method]
    assert np.all(np.asarray(est.norm.mean) == 0)  # exp(-1008) underflows even in float64
    assert np.all(np.isfinite(np.asarray(est.log_norm.mean)))
    assert np.all(np.asarray(est.ess) > 0.1 * N)  # the weights were scaled, not flushed to 0


def test_auto_gives_the_moments_and_the_evidence(key):
    offset = -3.0
    est = jaxmc.expectation(key, moments, log_posterior, LO, HI, n=N, args=offset)
    assert isinstance(est, jaxmc.Expectation) and isinstance(est.norm, jaxmc.Estimate)
    assert est.method in ("grid", "mixture")
    assert int(np.argmin(est.pilot)) == ("grid", "mixture").index(est.method)
    assert est.mean.shape == (D + 1, D) and est.ess.shape == (D + 1, D)
    assert np.all(np.abs(distinct((est.mean - TRUTH) / est.stderr)) < 5)
    evidence = math.exp(log_evidence(offset))
    assert abs(float(est.norm.mean) - evidence) < 5 * float(est.norm.stderr)
    assert abs(float(est.log_norm.mean) - log_evidence(offset)) < 5 * float(est.log_norm.stderr)
    # The evidence's relative error is the log evidence's error.
    np.testing.assert_allclose(float(est.norm.stderr / est.norm.mean), float(est.log_norm.stderr),
                               rtol=1e-9)
    assert "log_norm=Estimate(" in repr(est)


def test_auto_traces_under_jit_and_vmap():
    # Under jit the choice of "auto" is traced: both final stages are traced (lax.cond) and one
    # runs. Tracing alone checks that they agree; the numbers are the eager ones' code.
    run = jax.vmap(lambda k: jaxmc.expectation(k, moments, log_posterior, LO, HI, n=N, args=-3.0))
    est = jax.eval_shape(run, jax.random.split(jax.random.key(0), 4))
    assert est.method == "auto"
    assert est.mean.shape == (4, D + 1, D) and est.pilot.shape == (4, 2)
    assert est.log_norm.mean.shape == (4,) and est.mean.dtype == jnp.float64


def test_new_args_reuse_the_compiled_code(key):
    first = jaxmc.expectation(key, moments, log_posterior, LO, HI, n=N, method="mixture", args=-3.0)
    with compilations() as compiled:
        second = jaxmc.expectation(key, moments, log_posterior, LO, HI, n=N, method="mixture",
                                   args=-5.0)
    assert compiled == []
    # The same samples: only the scale of pi changed.
    np.testing.assert_allclose(np.asarray(second.mean), np.asarray(first.mean), rtol=1e-12)
    np.testing.assert_allclose(float(second.log_norm.mean), float(first.log_norm.mean) - 2.0, rtol=1e-12)


@pytest.mark.parametrize(
    "change, error, match",
    [
        (dict(method="vegas"), ValueError, "`method` must be one of"),
        (dict(n=1000), ValueError, "`n` must be >= 4096"),
        (dict(n=4096.0), TypeError, "`n` must be a Python int"),
        (dict(lo=HI, hi=LO), ValueError, "`lo` must be < `hi`"),
        (dict(lo=jnp.zeros(2)), ValueError, "same shape"),
        (dict(log_density=lambda x, a: x), ValueError, "`log_density` must return one scalar"),
        (dict(g="x"), TypeError, "`g` must be callable"),
        (dict(args=None), TypeError, "must accept 1 positional argument"),
        (dict(key=jax.random.split(jax.random.key(0), 2)), ValueError, "jax.vmap"),
        (dict(batched="yes"), TypeError, "`batched` must be a bool"),
    ],
)
def test_bad_input_is_refused_with_a_clear_error(change, error, match):
    call = dict(key=jax.random.key(0), g=moments, log_density=log_posterior, lo=LO, hi=HI, n=N,
                args=-3.0)
    call.update(change)
    with pytest.raises(error, match=match):
        jaxmc.expectation(call.pop("key"), call.pop("g"), call.pop("log_density"), call.pop("lo"),
                          call.pop("hi"), **call)
