"""Clear errors: every bad input or unsupported use names the argument and says what to do."""

import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmc
from jaxmc.proposals import GaussianMixture, Grid, Uniform

from .helpers import persistently_cached


KEY = jax.random.key(0)
LOG = lambda x: jnp.log(x[0] - 0.5)  # NaN on half the box
NONFINITE_FIX = re.escape("pass nonfinite='drop'")


def test_nonfinite_values_say_what_happened_and_what_to_do():
    # Outside jit: a FloatingPointError with the count.
    with pytest.raises(FloatingPointError, match=r"not finite.*" + NONFINITE_FIX):
        jaxmc.integrate(KEY, LOG, [0.0], [1.0], n=2**12)
    # Under jax.jit the error is a runtime one, and its text carries jaxmc's message.
    run = lambda k: jaxmc.integrate(k, LOG, [0.0], [1.0], n=2**12)
    with pytest.raises(jax.errors.JaxRuntimeError, match=r"jaxmc\.integrate: f\(x\)/p\(x\) was not finite.*"
                       + NONFINITE_FIX):
        jax.block_until_ready(jax.jit(run)(KEY))
    # Under equinox.filter_jit it is raised cleanly.
    with pytest.raises(eqx.EquinoxRuntimeError, match=NONFINITE_FIX):
        jax.block_until_ready(eqx.filter_jit(run)(KEY))
    # The fix the message names works, and counts the dropped samples.
    # (Dropped on request: counted, not warned about; `stats.unreliable` still says so.)
    est = jaxmc.integrate(KEY, LOG, [0.0], [1.0], n=2**12, nonfinite="drop")
    assert np.isfinite(est.mean) and 0 < int(est.n_nonfinite) < 2**12


def test_nonfinite_nan_poisons_the_estimate_and_leaves_a_cacheable_program():
    # nonfinite="nan": no runtime check; the estimate is NaN, counted and flagged, eagerly
    # (with the reliability warning) and under jit. A program under jit with "raise" holds
    # the check's host callback, which JAX's persistent cache refuses to store; with "nan"
    # it is stored.
    with pytest.warns(jaxmc.ReliabilityWarning, match="non-finite"):
        est = jaxmc.integrate(KEY, LOG, [0.0], [1.0], n=2**12, nonfinite="nan")
    assert np.isnan(est.mean) and np.isnan(est.variance) and int(est.n_nonfinite) > 0
    assert bool(jaxmc.stats.unreliable(est))

    def nonfinite_nan_run(k):
        return jaxmc.integrate(k, LOG, [0.0], [1.0], n=2**12, method="plain", nonfinite="nan")

    def nonfinite_raise_run(k):
        return jaxmc.integrate(k, lambda x: x[0], [0.0], [1.0], n=2**12, method="plain")

    traced = jax.jit(nonfinite_nan_run)(KEY)
    assert np.isnan(traced.mean) and int(traced.n_nonfinite) > 0
    jax.block_until_ready(jax.jit(nonfinite_raise_run)(KEY))
    assert persistently_cached("nonfinite_nan_run")
    assert not persistently_cached("nonfinite_raise_run")


def test_reverse_mode_through_a_tolerance_asks_for_a_fixed_n():
    def integral(t, **budget):
        return jaxmc.integrate(KEY, lambda x: t * x[0] ** 2, [0.0], [1.0], method="plain",
                               chunk=2**12, **budget).mean

    message = r"reverse-mode differentiation.*needs a fixed sample count.*Pass `n=`"
    with pytest.raises(RuntimeError, match=message):
        jax.grad(lambda t: integral(t, rtol=1e-2))(1.0)
    with pytest.raises(RuntimeError, match=message):  # at trace time under jit too
        jax.jit(jax.grad(lambda t: integral(t, atol=1e-2)))(1.0)
    # Forward mode through the tolerance loop works (reverse mode with a fixed n is
    # test_integrate.py::test_grad_with_fixed_budget).
    _, tangent = jax.jvp(lambda t: integral(t, rtol=1e-2), (1.0,), (1.0,))
    assert abs(float(tangent) - 1 / 3) < 0.02  # d/dt of t/3 = 1/3, to the 1% tolerance (6 sigma)


@pytest.mark.parametrize(
    "tolerances, error, match",
    [
        ({"rtol": "1e-3"}, TypeError, "`rtol` must be a real number"),
        ({"atol": "0.1"}, TypeError, "`atol` must be a real number"),
        ({"rtol": True}, TypeError, "`rtol` must be a real number"),
        ({"rtol": -1e-3}, ValueError, "`rtol` must be a finite number >= 0"),
        ({"atol": float("nan")}, ValueError, "`atol` must be a finite number >= 0"),
        ({"rtol": float("inf")}, ValueError, "`rtol` must be a finite number >= 0"),
        ({"rtol": [1e-3, 1e-3]}, ValueError, r"`rtol` must be a scalar.*shape \(2,\)"),
        ({"atol": jnp.ones(2)}, ValueError, r"`atol` must be a scalar"),
    ],
)
def test_bad_tolerances_name_the_argument(tolerances, error, match):
    with pytest.raises(error, match=match):
        jaxmc.integrate(KEY, lambda x: x[0], [0.0], [1.0], **tolerances)


def test_rtol_below_the_dtype_floor_asks_for_float64():
    f = lambda x: x[0]
    floor32 = jaxmc.stats.rounding_floor(jnp.float32)
    lo32, hi32 = jnp.zeros(1, jnp.float32), jnp.ones(1, jnp.float32)  # a float32 integration
    with pytest.raises(ValueError, match=r"`rtol`=1e-09 is below what float32.*float64"):
        jaxmc.integrate(KEY, f, lo32, hi32, rtol=1e-9)
    with pytest.raises(ValueError, match=r"`rtol`.*below what float32"):
        jaxmc.integrate(KEY, f, lo32, hi32, rtol=floor32 / 2, atol=1e-3)
    with pytest.raises(ValueError, match=r"`rtol`=1e-17 is below what float64"):
        jaxmc.integrate(KEY, f, [0.0], [1.0], rtol=1e-17)
    # At the floor and above it, and rtol=0 with an atol, are accepted (the floor is not a
    # wall: the run stops at the budget here).
    with pytest.warns(jaxmc.ReliabilityWarning, match="tolerance was not met"):
        est = jaxmc.integrate(KEY, f, lo32, hi32, rtol=floor32, max_n=2**12, method="plain")
    assert est.n == 2**12
    est = jaxmc.integrate(KEY, f, lo32, hi32, rtol=0.0, atol=0.05, method="plain")
    assert est.converged


def test_an_atol_below_the_rounding_floor_stops_there_and_says_so():
    # float32's floor for this integral is 4.8e-7 x 0.42 = 2e-7: no budget meets atol=1e-12.
    # The stream stops where its error bar reaches the floor, not at max_n (which it spent
    # before, 2^30 by default), and the warning says why and what would meet it.
    f = lambda x: jnp.exp(-jnp.sum(x**2))
    lo32, hi32 = jnp.zeros(3, jnp.float32), jnp.ones(3, jnp.float32)
    with pytest.warns(jaxmc.ReliabilityWarning,
                      match=r"rounding floor of float32.*float64.*at least 2.0e-07 \(`atol`"):
        est = jaxmc.integrate(KEY, f, lo32, hi32, atol=1e-12, max_n=2**26, method="qmc")
    assert not est.converged and est.n <= 2**20
    floor = jaxmc.stats.rounding_floor(jnp.float32) * est.mean
    np.testing.assert_allclose(est.stderr, floor, rtol=1e-3)
    assert abs(float(est.mean) - 0.41653838588663810) < 5 * float(est.stderr)


def test_batched_shape_error_speaks_of_the_users_batch():
    wrong = lambda x: x[:3, 0]  # not one value per point
    messages = []
    for call in (
        lambda: jaxmc.integrate(KEY, wrong, [0.0, 0.0], [1.0, 1.0], n=2**12, batched=True),
        lambda: jaxmc.integrate(KEY, wrong, [0.0, 0.0], [1.0, 1.0], n=2**20, batched=True),
        lambda: jaxmc.uniform(KEY, wrong, [0.0, 0.0], [1.0, 1.0], 1000, batched=True),
        lambda: jaxmc.randomized_qmc(KEY, wrong, [0.0, 0.0], [1.0, 1.0], 64, batched=True),
    ):
        with pytest.raises(ValueError, match=r"`f` with batched=True .* shape \(batch, 2\)") as info:
            call()
        messages.append(str(info.value))
    # Whatever the budget and the estimator (hence the internal block), the same words.
    assert len(set(messages)) == 1, messages
    assert "returned shape (3,)" in messages[0]
    assert not re.search(r"\d{3,}", messages[0]), messages[0]


def _entry_points():
    """Each entry point as `call(key=..., f=..., lo=..., hi=..., n=..., batched=...)`."""
    def grid(lo, hi):
        return Grid(lo, hi, bins=8)

    def mixture(lo, hi):
        return GaussianMixture(jax.random.key(1), lo, hi, 2)

    return {
        "integrate": lambda key, f, lo, hi, n, batched: jaxmc.integrate(
            key, f, lo, hi, n=n, batched=batched),
        "uniform": lambda key, f, lo, hi, n, batched: jaxmc.uniform(
            key, f, lo, hi, n, batched=batched),
        "importance": lambda key, f, lo, hi, n, batched: jaxmc.importance(
            key, f, Uniform(lo, hi), n, batched=batched),
        "stratified": lambda key, f, lo, hi, n, batched: jaxmc.stratified(
            key, f, lo, hi, (4,) * len(lo), per_stratum=n, batched=batched),
        "randomized_qmc": lambda key, f, lo, hi, n, batched: jaxmc.randomized_qmc(
            key, f, lo, hi, n, batched=batched),
        "adapt": lambda key, f, lo, hi, n, batched: jaxmc.fit.adapt(
            key, f, grid(lo, hi), iterations=2, n_per_iteration=n, batched=batched),
        "fit": lambda key, f, lo, hi, n, batched: jaxmc.fit.fit(
            key, f, mixture(lo, hi), n, max_steps=1, batched=batched),
    }


GOOD = {"key": KEY, "f": lambda x: jnp.sum(x), "lo": [0.0, 0.0], "hi": [1.0, 1.0], "n": 64,
        "batched": False}
BAD_INPUTS = [
    ({"lo": [1.0, 0.0]}, ValueError, r"`lo` must be < `hi`"),
    ({"hi": [1.0, 0.0]}, ValueError, r"`lo` must be < `hi`"),
    ({"lo": [0.0, 0.0, 0.0]}, ValueError, r"`lo` and `hi` must have the same shape"),
    ({"lo": [0.0, float("nan")]}, ValueError, r"`lo` and `hi` must not be NaN"),
    ({"lo": ["a", "b"]}, TypeError, r"`lo` must be a real number or a sequence of them"),
    ({"hi": [1.0 + 1j, 1.0]}, TypeError, r"`hi` must be a real number or a sequence of them"),
    ({"n": 0}, ValueError, r"`(n|n_per_iteration|per_stratum)` must be >= [12]"),
    ({"n": -3}, ValueError, r"`(n|n_per_iteration|per_stratum)` must be >= [12]"),
    ({"n": 64.0}, TypeError, r"`(n|n_per_iteration|per_stratum)` must be a Python int"),
    ({"n": 2**40}, ValueError, r"`(n|n_per_iteration|per_stratum)`.* must be at most 2\*\*31 - 1"),
    ({"f": "x**2"}, TypeError, r"`f` must be callable"),
    ({"f": lambda x, y: x}, TypeError, r"`f` must accept 1 positional argument"),
    ({"f": lambda x: "one"}, TypeError, r"`f` must return a real number or an array of real numbers, got str"),
    ({"f": lambda x: x[0] + 1j}, TypeError, r"`f` must return a real number .*got dtype complex"),
    ({"f": lambda x: x[0], "batched": True}, ValueError, r"`f` with batched=True .* one value per point"),
    ({"batched": "yes"}, TypeError, r"`batched` must be a bool"),
    ({"key": 0}, TypeError, r"`key` must be a JAX PRNG key"),
    ({"key": jnp.zeros(3)}, TypeError, r"`key` must be a JAX PRNG key"),
    ({"key": jax.random.split(KEY, 2)}, ValueError, r"`key` must be a single key"),
]


@pytest.mark.parametrize("name", list(_entry_points()))
def test_bad_inputs_name_the_argument(name):
    call = _entry_points()[name]
    for change, error, match in BAD_INPUTS:
        with pytest.raises(error, match=match):
            call(**{**GOOD, **change})


def test_strata_beyond_int32_are_refused_however_large():
    # 2^31 strata per axis in 3-D: 2^93 cells, whose NumPy product wrapped around to 0.
    with pytest.raises(ValueError, match="per_stratum"):
        jaxmc.stratified(jax.random.key(0), lambda x: x[0], jnp.zeros(3), jnp.ones(3),
                         (2**31,) * 3)
