"""`integrate(method="auto")`'s density along one direction (`"ridge_qmc"`, `_ridge`)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import dblquad

import jaxmc
from jaxmc._estimators._ridge import RIDGE_DEFENSIVE, profiled_ridge, ridge_direction

from .helpers import assert_eager_method_honest, auto_against, box


# A Breit-Wigner resonance in s = w . x, off the axes (as the `auto` benchmark's).
W3 = np.array([1.0, 1.5, 2.0]) / np.linalg.norm([1.0, 1.5, 2.0])
WIDTH, CENTRE = 0.01, float(0.4 * W3.sum())


def resonance(x):
    return (WIDTH / np.pi) / ((x @ jnp.asarray(W3, x.dtype) - CENTRE) ** 2 + WIDTH**2)


@pytest.fixture(scope="module")
def resonance_exact():
    # Over x_3 in closed form (the arctangent), then x_1, x_2 by quadrature.
    def inner(x2, x1):
        c = W3[0] * x1 + W3[1] * x2
        top, bottom = (np.arctan((c + t * W3[2] - CENTRE) / WIDTH) for t in (1.0, 0.0))
        return (top - bottom) / (np.pi * W3[2])

    value, error = dblquad(inner, 0, 1, 0, 1, epsabs=1e-13, epsrel=1e-12)
    assert error < 1e-10
    return value


STEPS = 2048


def _profiled():
    lo, hi = box(3)
    return profiled_ridge(lo, hi, jnp.asarray(W3), 2, f=resonance, batched=False, steps=STEPS)


def test_the_ridge_map_has_the_density_it_reports():
    # q(x) is the inverse of the map's Jacobian determinant, at points over the whole cube
    # (on the profile: steep steps near the resonance, the defensive share far off).
    trained = _profiled()
    u = jax.random.uniform(jax.random.key(1), (512, 3), jnp.float64)
    x, q, _ = trained.unit_map(u)
    jacobians = jax.vmap(jax.jacfwd(lambda v: trained.unit_map(v[None])[0][0]))(u)
    np.testing.assert_allclose(np.abs(np.linalg.det(jacobians)) * q, 1.0, rtol=1e-8)
    # Only the coordinate along w's largest component (axis 2) is drawn; the others are u's.
    np.testing.assert_array_equal(np.asarray(x[:, :2]), np.asarray(u[:, :2]))
    # ...and it is a density on the box: q's mean over uniform points (the integral of
    # q^2 / q) and 1/q's (the box's volume) are finite, and E_q[1/q] = 1 up to 5 sigma.
    _, log_q = trained.map(u)
    weights = np.exp(-np.asarray(log_q))
    assert abs(weights.mean() - 1) < 5 * weights.std() / np.sqrt(len(weights))
    # Every step of the table keeps its defensive share of the mass.
    assert np.diff(np.asarray(trained.levels)).min() >= 0.999 * RIDGE_DEFENSIVE / STEPS


def test_the_profile_flattens_the_resonance(resonance_exact):
    # Plain MC through the map: f/q is nearly flat where the window over x_3 holds the
    # resonance, bounded everywhere (no power-law tail), 50x less relative variance than
    # on uniform points.
    from jaxmc._diagnostics import pareto_k, tail_of

    ridge = _profiled()
    u = jax.random.uniform(jax.random.key(2), (2**15, 3), jnp.float64)
    x, log_q = ridge.map(u)
    through = np.asarray(resonance(x) / jnp.exp(log_q)) / resonance_exact
    uniform = np.asarray(resonance(u)) / resonance_exact
    assert abs(through.mean() - 1) < 5 * through.std() / np.sqrt(len(through))
    assert through.var() < uniform.var() / 50, (through.var(), uniform.var())
    assert through.max() < 1.5 * np.median(through)
    assert float(pareto_k(tail_of(jnp.asarray(through)[:, None]))[0]) < 0


def test_the_gradients_find_a_ridge_and_only_a_ridge():
    lo, hi = box(3)
    x = jax.random.uniform(jax.random.key(3), (256, 3), jnp.float64)

    def direction(f):
        w, ridge, axis = ridge_direction(f, False, lo, hi, x, jnp.abs(jax.vmap(f)(x)))
        assert int(axis) == int(np.argmax(np.abs(np.asarray(w))))
        return np.asarray(w), bool(ridge)

    w, ridge = direction(resonance)
    assert ridge and abs(abs(w @ W3) - 1) < 1e-10
    corner = lambda v: (1 + v @ jnp.asarray([0.5, 1.0, 2.0])) ** -4.0  # noqa: E731
    w, ridge = direction(corner)
    assert ridge and abs(abs(w @ np.array([0.5, 1, 2])) / np.linalg.norm([0.5, 1, 2]) - 1) < 1e-10
    # Not a ridge: a round peak, a product, an indicator (no gradient at all).
    for f in (lambda v: jnp.exp(-jnp.sum((v - 0.5) ** 2) / 0.01),
              lambda v: jnp.prod(jnp.cos(v)),
              lambda v: (jnp.sum(v) < 1.2).astype(v.dtype)):
        assert not direction(f)[1]


def test_auto_takes_the_ridge_on_an_oblique_resonance(resonance_exact):
    # 30-90x less error than QMC alone, on the same budget, with an honest error bar.
    n = 2**17
    rms, runs = auto_against(resonance, resonance_exact, *box(3), n, "ridge_qmc", "qmc")
    for est in runs:
        assert est.pilot.candidates[-1] == "ridge_qmc"
        assert int(est.n) <= n and sum(est.pilot.evaluations) < n / 8
    assert rms["auto"] < rms["qmc"] / 10, rms


def test_the_ridge_stream_is_unbiased_and_honest(resonance_exact):
    # Over the keys that took the ridge (at least 40 of 48).
    assert_eager_method_honest(resonance, resonance_exact, *box(3), 2**15, "ridge_qmc",
                               range(100, 148), least=40)


def test_the_ridge_serves_float32(resonance_exact):
    # In float32 (bounds in float32): the gradients still read parallel, the map's density
    # matches its Jacobian, and the estimate is within 5 of its standard errors.
    lo, hi = (b.astype(jnp.float32) for b in box(3))
    est = jaxmc.integrate(jax.random.key(1), resonance, lo, hi, n=2**17)
    assert est.method == "ridge_qmc" and est.mean.dtype == jnp.float32, est.pilot
    assert abs(float(est.mean) - resonance_exact) < 5 * float(est.stderr) + 1e-6
    ridge = profiled_ridge(lo, hi, jnp.asarray(W3, jnp.float32), 2, f=resonance,
                           batched=False, steps=STEPS)
    u = jax.random.uniform(jax.random.key(1), (256, 3), jnp.float32)
    _, q, _ = ridge.unit_map(u)
    jacobians = jax.vmap(jax.jacfwd(lambda v: ridge.unit_map(v[None])[0][0]))(u)
    np.testing.assert_allclose(np.abs(np.linalg.det(jacobians)) * q, 1.0, rtol=1e-3)
