"""`args`: parameters passed as `f(x, args)` give the closure's numbers and reuse compiled code.

Every entry point that takes an integrand also takes `args`; the result matches
the equivalent closure, gradients flow into `args`, and a second call with new
values of the same shapes compiles nothing (counted with `jax.log_compiles`).
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmc
from jaxmc._integrand import bind
from jaxmc.proposals import Grid, Uniform

from .helpers import compilations


LO, HI = jnp.zeros(2), jnp.ones(2)
FIRST, SECOND = (0.4, 0.05), (0.6, 0.1)  # (centre, width) of the Gaussian bump


def bump(x, args):
    """A Gaussian bump on the unit square; `args = (centre, width)`."""
    centre, width = args
    return jnp.exp(-jnp.sum((x - centre) ** 2) / width)


def bump_integral(args):
    """The bump's exact integral over the unit square."""
    c, w = args
    one = math.sqrt(math.pi * w) / 2 * (math.erf((1 - c) / math.sqrt(w)) + math.erf(c / math.sqrt(w)))
    return one**2


def closure(args):
    return lambda x: bump(x, args)


def assert_same(a, b, rtol=1e-12):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=0)


def estimate_arrays(est):
    return (est.mean, est.variance, est.n, est.n_nonfinite)


# 256 evaluations each, and the cheapest proposals: the estimators run eagerly, and the
# primitives compiled for one shape serve them all.
PROPOSALS = [Uniform(LO, HI), Uniform(LO, HI)]
ESTIMATORS = {
    "uniform": lambda key, f, **kw: jaxmc.uniform(key, f, LO, HI, 256, **kw),
    "importance": lambda key, f, **kw: jaxmc.importance(key, f, PROPOSALS[0], 256, **kw),
    "stratified": lambda key, f, **kw: jaxmc.stratified(key, f, LO, HI, (16, 8), **kw),
    "randomized_qmc": lambda key, f, **kw: jaxmc.randomized_qmc(key, f, LO, HI, 64, replicas=4, **kw),
    "mis": lambda key, f, **kw: jaxmc.mis(key, f, PROPOSALS, 128, **kw),
    "mis_one_sample": lambda key, f, **kw: jaxmc.mis_one_sample(
        key, f, PROPOSALS, jnp.array([0.5, 0.5]), 256, **kw
    ),
    "antithetic": lambda key, f, **kw: jaxmc.antithetic(key, f, LO, HI, 256, **kw),
}


@pytest.mark.parametrize("name", ESTIMATORS)
def test_estimators_take_args(key, name):
    estimator = ESTIMATORS[name]
    with_args = estimator(key, bump, args=FIRST)
    assert_same(estimate_arrays(with_args), estimate_arrays(estimator(key, closure(FIRST))))
    if name in ("uniform", "importance"):
        with compilations() as compiled:
            again = estimator(key, bump, args=SECOND)
        assert compiled == []
        assert_same(estimate_arrays(again), estimate_arrays(estimator(key, closure(SECOND))))


def test_control_variate_passes_args_to_f_and_g(key):
    g = lambda x, args: 1.0 + args[0] * jnp.sum(x)
    g_integral = 1.0 + FIRST[0]  # over the unit square
    a = jaxmc.control_variate(key, bump, g, g_integral, LO, HI, 256, args=FIRST)
    b = jaxmc.control_variate(
        key, closure(FIRST), lambda x: g(x, FIRST), g_integral, LO, HI, 256
    )
    assert_same(estimate_arrays(a), estimate_arrays(b))


def test_batched_integrand_gets_the_batch_and_args(key):
    batch = lambda x, args: jax.vmap(bump, in_axes=(0, None))(x, args)
    a = jaxmc.uniform(key, batch, LO, HI, 256, batched=True, args=FIRST)
    assert_same(estimate_arrays(a), estimate_arrays(jaxmc.uniform(key, bump, LO, HI, 256, args=FIRST)))


def test_numbers_in_args_are_traced_ints_and_bools_stay_static():
    """Floats (and NumPy values) become arrays, traced by the compiled code; Python ints and
    bools stay static, as `equinox.filter_jit` treats them (they may set shapes)."""
    bound = bind(bump, {"w": 0.5, "c": np.float64(0.1), "k": 3, "flag": True, "a": jnp.ones(2)})
    assert all(isinstance(bound.args[name], jax.Array) for name in ("w", "c", "a"))
    assert bound.args["k"] == 3 and type(bound.args["k"]) is int and bound.args["flag"] is True
    assert bind(bump, None) is bump


def test_args_must_be_accepted():
    with pytest.raises(TypeError, match="2 positional arguments"):
        jaxmc.uniform(jax.random.key(0), lambda x: x, 0.0, 1.0, 16, args=1.0)


@pytest.mark.parametrize("method", ["plain", "qmc", "adaptive", "auto"])
def test_integrate_reuses_its_compiled_code(key, method):
    """A second call with new parameter values compiles nothing, and integrates the new bump.
    (`"auto"` under `jit`: eagerly its pilot may end at another stage for other values, and
    compile that stage's programs; traced, every stage is one program.)"""
    run = lambda args: jaxmc.integrate(key, bump, LO, HI, n=2**15, chunk=2**12, method=method, args=args)
    if method == "auto":
        run = jax.jit(run)
    first = run(FIRST)
    with compilations() as compiled:
        second = run(SECOND)
    assert first.method == second.method
    assert compiled == []
    for est, args in ((first, FIRST), (second, SECOND)):
        assert abs(float(est.mean) - bump_integral(args)) < 5 * float(est.stderr)


def test_gradients_reach_args(key):
    """Value and gradient in `args` match the closure's, for `uniform` and `integrate(n=...)`."""
    centre = FIRST[0]

    def estimate(estimator, through_args):
        if through_args:
            return lambda w: estimator(bump, args=(centre, w)).mean
        return lambda w: estimator(lambda x: bump(x, (centre, w))).mean

    for estimator in (
        lambda f, **kw: jaxmc.uniform(key, f, LO, HI, 256, **kw),
        lambda f, **kw: jaxmc.integrate(key, f, LO, HI, n=4096, method="plain", **kw),
    ):
        value, grad = jax.value_and_grad(estimate(estimator, True))(FIRST[1])
        assert_same((value, grad), jax.value_and_grad(estimate(estimator, False))(FIRST[1]))
        assert float(grad) > 0  # a wider bump holds more


def _scaled_peak(x, a):
    """`a` times a normalised 4-D Gaussian of sd 0.03 at 0.3: integral `a` (to ~1e-20)."""
    return a * jnp.exp(-jnp.sum((x - 0.3) ** 2) / (2 * 0.03**2)) / (2 * jnp.pi * 0.03**2) ** 2


def _scaled_broad_peak(x, a):
    """`a` times a normalised 4-D Gaussian of sd 0.1 / sqrt(2) at the centre: integral `a`
    (to ~1e-11)."""
    return a * jnp.exp(-jnp.sum((x - 0.5) ** 2) / 0.1**2) / (0.1 * jnp.sqrt(jnp.pi)) ** 4


def _scaled_two_peaks(x, a):
    """`a` times the mean of two normalised 4-D Gaussians of sd 0.03 at 1/3 and 2/3: integral
    `a` (to ~1e-20)."""
    return (_scaled_peak(x + 0.3 - 1 / 3, a) + _scaled_peak(x + 0.3 - 2 / 3, a)) / 2


def _two_peaks_or_broad_peak(x, args):
    """`_scaled_two_peaks`, or where `broad` `_scaled_broad_peak`, of `a`: as `args`,
    `broad` is an input of the same compiled programs for both."""
    a, broad = args
    return jnp.where(broad, _scaled_broad_peak(x, a), _scaled_two_peaks(x, a))


@pytest.mark.parametrize("method", ["adaptive", "grid_qmc", "importance", "auto"])
def test_derivatives_hold_fitted_densities_fixed(method):
    # Each method fits a density to the integrand's values (the grid, QMC through it, a
    # mixture seeded from it; auto's winner, its choice traced under grad). The derivative
    # holds it fixed, sum_i w_i df/da(x_i) / q(x_i), an unbiased estimate of dI/da: for
    # f = a * peak it is the estimate over a. Through the fits (EM's weights |f|, VEGAS's
    # histograms) it was NaN where f underflowed to 0.
    lo, hi = jnp.zeros(4), jnp.ones(4)
    for broad in (False, True):

        def run(a, broad=broad):
            return jaxmc.integrate(jax.random.key(0), _two_peaks_or_broad_peak, lo, hi,
                                   n=100_000, method=method, args=(a, jnp.asarray(broad))).mean

        value, grad = jax.value_and_grad(run)(2.0)
        np.testing.assert_allclose(grad, value / 2, rtol=1e-10)
        assert abs(float(value) - 2) < 0.01


def test_fit_and_adapt_reuse_their_compiled_code(key):
    grid = Grid(LO, HI, 16)
    fit = lambda f, **kw: jaxmc.fit.fit(key, f, grid, 1024, max_steps=3, **kw)
    adapt = lambda k, f, **kw: jaxmc.fit.adapt(
        k, f, grid, iterations=3, n_per_iteration=1024, stratify=False, **kw
    )
    est, adapted = adapt(key, bump, args=FIRST)
    est_closure, adapted_closure = adapt(key, closure(FIRST))
    assert_same((est.mean, est.variance, adapted.edges),
                (est_closure.mean, est_closure.variance, adapted_closure.edges))
    # `fit`'s default for a grid is the same VEGAS rounds (so it matches the closure too).
    np.testing.assert_array_equal(fit(bump, args=FIRST).proposal.edges, adapted.edges)
    with compilations() as compiled:
        fitted = fit(bump, args=SECOND)
        est, adapted = adapt(key, bump, args=SECOND)
    assert compiled == []
    np.testing.assert_array_equal(fitted.proposal.edges, adapted.edges)
    assert abs(float(est.mean) - bump_integral(SECOND)) < 5 * float(est.stderr)
    # `chain` of one stage is `adapt` with a folded key (and runs the same compiled loop).
    stage = jaxmc.fit.Stage(jaxmc.fit.Vegas(), iterations=3, n_per_iteration=1024)
    chained, _ = jaxmc.fit.chain(key, bump, grid, [stage], args=SECOND)
    expected, _ = adapt(jax.random.fold_in(key, 0), bump, args=SECOND)
    assert_same((chained.mean, chained.variance), (expected.mean, expected.variance))


@pytest.mark.parametrize("rule", [jaxmc.quad.midpoint, jaxmc.quad.gauss_legendre])
def test_quadrature_takes_args_without_recompiling(rule):
    f = lambda x, a: jnp.exp(a * jnp.sum(x))  # noqa: E731
    lo, hi = jnp.zeros(2), jnp.ones(2)
    first = rule(f, lo, hi, 8, args=0.5)
    np.testing.assert_allclose(first, rule(lambda x: jnp.exp(0.5 * jnp.sum(x)), lo, hi, 8), rtol=1e-12)
    with compilations() as compiled:
        second = rule(f, lo, hi, 8, args=1.5)
    assert not compiled, compiled
    np.testing.assert_allclose(second, rule(lambda x: jnp.exp(1.5 * jnp.sum(x)), lo, hi, 8), rtol=1e-12)
    np.testing.assert_allclose(second, ((math.exp(1.5) - 1) / 1.5) ** 2, rtol=1e-2)
