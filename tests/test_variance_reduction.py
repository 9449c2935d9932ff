"""Variance reduction: stratified, MIS (multi- and one-sample), control and antithetic variates.

Statistical checks run each estimator under `jit(vmap)` over K = 400 fixed keys
(`helpers.run_keys`) and test two things (`helpers.assert_unbiased_and_honest`):
unbiasedness (the average of the K estimates is within 5 of its standard errors of
the integral, i.e. the mean z-score is within 5/sqrt(K) of 0) and an honest variance
(the empirical variance of the K estimates matches the mean reported variance within
a chi-square band of 5 standard deviations, sqrt(2/(K-1)) relative). Randomised QMC
has its own file, test_vr_qmc.py.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmc._estimators._stratified import snake_order  # a private helper, tested directly
from jaxmc.estimators import (
    antithetic,
    control_variate,
    importance,
    mis,
    mis_one_sample,
    stratified,
    uniform,
)

from .helpers import (
    SMOOTH2,
    SMOOTH2_HI,
    SMOOTH2_LO,
    assert_unbiased_and_honest,
    run_keys,
    smooth2,
    tilted,
    tilted_da,
    tilted_da_integral,
)


class Normal(eqx.Module):
    """A 1-D Gaussian proposal on the real line (test stub)."""

    mu: jax.Array
    sigma: jax.Array

    def __init__(self, mu, sigma):
        self.mu = jnp.asarray(mu, dtype=float)
        self.sigma = jnp.asarray(sigma, dtype=float)

    def sample(self, key, n):
        x = self.mu + self.sigma * jax.random.normal(key, (n,))
        return x, self.pdf(x)

    def pdf(self, x):
        return jnp.exp(-0.5 * ((x - self.mu) / self.sigma) ** 2) / (self.sigma * jnp.sqrt(2 * jnp.pi))


class Fixed(eqx.Module):
    """A proposal stub that 'samples' given points (ignores the key) with a given pdf."""

    points: jax.Array
    mu: jax.Array
    sigma: jax.Array

    def sample(self, key, n):
        assert n == self.points.shape[0]
        return self.points, self.pdf(self.points)

    def pdf(self, x):
        return Normal(self.mu, self.sigma).pdf(x)


# --- stratified --------------------------------------------------------------


def test_snake_order_visits_every_cell_through_faces():
    for counts in [(1,), (5,), (2, 3), (3, 3, 2), (4, 1, 3)]:
        order = snake_order(counts)
        assert sorted(order) == list(range(int(np.prod(counts))))
        cells = np.stack(np.unravel_index(order, counts), -1)
        assert np.all(np.abs(np.diff(cells, axis=0)).sum(axis=1) == 1)


def test_stratified_unbiased_and_honest_vector_output():
    lo, hi = SMOOTH2_LO, SMOOTH2_HI
    est = run_keys(lambda k: stratified(k, smooth2, lo, hi, (4, 3), per_stratum=3), 1)
    assert est.n[0] == 36 and est.mean.shape == (400, 2)
    assert_unbiased_and_honest(est, SMOOTH2)


def test_stratified_scalar_bounds_default_per_stratum():
    est = run_keys(lambda k: stratified(k, jnp.exp, -1.0, 1.0, 5), 2)
    assert est.n[0] == 10
    assert_unbiased_and_honest(est, np.e - np.exp(-1))


@pytest.mark.parametrize("counts", [(4, 4), (5, 3), (3, 1)])
def test_stratified_one_per_stratum_is_unbiased_and_not_optimistic(counts):
    # (5, 3) and (3, 1) have an odd number of strata: the last three collapse as a triple.
    lo, hi = SMOOTH2_LO, SMOOTH2_HI
    est = run_keys(lambda k: stratified(k, smooth2, lo, hi, counts, per_stratum=1), 3)
    ratio = assert_unbiased_and_honest(est, SMOOTH2, honest="conservative")
    # Collapsing overstates by the neighbours' mean differences, but stays in bounds
    # for a smooth integrand.
    assert np.all(ratio > 0.05), ratio


def test_stratified_one_stratum_one_point_has_infinite_variance(key):
    est = stratified(key, jnp.sin, 0.0, 1.0, 1, per_stratum=1)
    assert np.isinf(est.variance)


def test_stratified_beats_plain_at_equal_n():
    lo, hi = SMOOTH2_LO, SMOOTH2_HI
    f = lambda x: smooth2(x)[0]
    strat = run_keys(lambda k: stratified(k, f, lo, hi, (8, 8), per_stratum=2), 4)
    plain = run_keys(lambda k: uniform(k, f, lo, hi, 128), 5)
    v_strat, v_plain = strat.mean.var(), plain.mean.var()
    # Within-stratum variance ~ (cell size)^2: ~M times smaller than plain.
    assert v_strat < v_plain / 20, (v_strat, v_plain)
    assert strat.variance.mean() < plain.variance.mean() / 20


def test_stratified_points_cover_their_cells(key):
    seen = []

    def f(x):
        seen.append(x)
        return jnp.sum(x, axis=-1)

    stratified(key, f, jnp.zeros(2), jnp.ones(2), (4, 2), per_stratum=3, batched=True)
    x = np.asarray(seen[0]).reshape(8, 3, 2)
    cells = np.floor(x * np.array([4, 2])).astype(int)
    expected = np.stack(np.unravel_index(np.arange(8), (4, 2)), -1)
    assert np.all(cells == expected[:, None, :])


def test_stratified_bad_inputs(key):
    lo, hi = jnp.zeros(2), jnp.ones(2)
    with pytest.raises(ValueError, match="counts"):
        stratified(key, smooth2, lo, hi, (4,))
    with pytest.raises(TypeError, match="counts"):
        stratified(key, smooth2, lo, hi, 4)
    with pytest.raises(ValueError, match=r"counts\[1\]"):
        stratified(key, smooth2, lo, hi, (4, 0))
    with pytest.raises(TypeError, match=r"counts\[0\]"):
        stratified(key, smooth2, lo, hi, (2.5, 2))
    with pytest.raises(ValueError, match="per_stratum"):
        stratified(key, smooth2, lo, hi, (2, 2), per_stratum=0)
    with pytest.raises(ValueError, match="`lo` must be < `hi`"):
        stratified(key, smooth2, hi, lo, (2, 2))
    with pytest.raises(ValueError, match="counts"):
        stratified(key, jnp.sin, 0.0, 1.0, (2, 2))
    with pytest.raises(TypeError, match="key"):
        stratified(0, jnp.sin, 0.0, 1.0, 4)


# --- multiple importance sampling ---------------------------------------------


def two_peaks(x):
    # A narrow peak at -2 and a broad one at 2; integral 1.5.
    return Normal(-2.0, 0.3).pdf(x) + 0.5 * Normal(2.0, 1.5).pdf(x)


NARROW, BROAD = Normal(-2.0, 0.35), Normal(2.0, 1.7)


@pytest.mark.parametrize(
    "heuristic, beta, counts", [("balance", 2.0, (60, 40)), ("power", 2.0, (60, 40)), ("power", 3.5, 50)]
)
def test_mis_unbiased_and_honest(heuristic, beta, counts):
    est = run_keys(
        lambda k: mis(k, two_peaks, [NARROW, BROAD], counts, heuristic=heuristic, beta=beta), 10
    )
    assert est.n[0] == 100
    assert_unbiased_and_honest(est, 1.5)


@pytest.mark.parametrize("heuristic", ["balance", "power"])
def test_mis_one_sample_unbiased_and_honest(heuristic):
    probs = jnp.array([0.3, 0.7])
    est = run_keys(
        lambda k: mis_one_sample(k, two_peaks, [NARROW, BROAD], probs, 100, heuristic=heuristic), 11
    )
    assert_unbiased_and_honest(est, 1.5)


def test_mis_weights_match_the_assignment_formulas():
    # Deterministic stubs: the points are fixed, so the estimate is a known sum.
    xa = jnp.array([-2.1, -1.5, 0.3])
    xb = jnp.array([1.0, 2.5, -2.0])
    pa, pb = Fixed(xa, -2.0, 0.5), Fixed(xb, 2.0, 1.0)
    f = two_peaks
    key = jax.random.key(0)
    jmis = lambda *args, **kw: jax.jit(lambda k: mis(k, *args, **kw))(key)

    def pdfs(x):
        return np.asarray(pa.pdf(x)), np.asarray(pb.pdf(x))

    (a1, b1), (a2, b2) = pdfs(xa), pdfs(xb)
    fa, fb = np.asarray(f(xa)), np.asarray(f(xb))
    # Balance heuristic, equal counts: w_k = p_k / sum_l p_l (the assignment).
    expected = np.mean(a1 / (a1 + b1) * fa / a1) + np.mean(b2 / (a2 + b2) * fb / b2)
    np.testing.assert_allclose(jmis(f, [pa, pb], 3).mean, expected, rtol=1e-12)
    # Power heuristic, beta = 2.
    expected = np.mean(a1**2 / (a1**2 + b1**2) * fa / a1) + np.mean(b2**2 / (a2**2 + b2**2) * fb / b2)
    np.testing.assert_allclose(jmis(f, [pa, pb], 3, heuristic="power").mean, expected, rtol=1e-12)
    # Balance with unequal counts: w_k = n_k p_k / sum_l n_l p_l.
    pb4 = Fixed(jnp.concatenate([xb, jnp.array([0.0])]), 2.0, 1.0)
    xb4 = np.asarray(pb4.points)
    a4, b4 = pdfs(xb4)
    fb4 = np.asarray(f(xb4))
    expected = np.mean(fa / (a1 + 4 / 3 * b1)) + np.mean(fb4 / (3 / 4 * a4 + b4))
    np.testing.assert_allclose(jmis(f, [pa, pb4], (3, 4)).mean, expected, rtol=1e-12)
    # One-sample balance with equal probabilities: f / (c_I sum_l p_l), whatever I is,
    # when both techniques propose the same points.
    pa2 = Fixed(xa, 2.0, 1.0)
    a, b = np.asarray(pa.pdf(xa)), np.asarray(pa2.pdf(xa))
    expected = np.mean(fa / (0.5 * (a + b)))
    got = jax.jit(lambda k: mis_one_sample(k, f, [pa, pa2], jnp.array([0.5, 0.5]), 3))(key)
    np.testing.assert_allclose(got.mean, expected, rtol=1e-12)


def test_power_heuristic_with_beta_one_is_balance(key):
    probs = jnp.array([0.4, 0.6])

    @jax.jit
    def both(k):
        return [
            (fn(), fn(heuristic="power", beta=1.0))
            for fn in (
                lambda **kw: mis(k, two_peaks, [NARROW, BROAD], (30, 20), **kw),
                lambda **kw: mis_one_sample(k, two_peaks, [NARROW, BROAD], probs, 50, **kw),
            )
        ]

    for a, b in both(key):
        np.testing.assert_allclose(a.mean, b.mean, rtol=1e-12)
        np.testing.assert_allclose(a.variance, b.variance, rtol=1e-10)


def test_mis_beats_the_worse_strategy_and_is_close_to_the_better():
    n = 200
    est_mis = run_keys(lambda k: mis(k, two_peaks, [NARROW, BROAD], (n // 2, n // 2)), 12)
    est_a = run_keys(lambda k: importance(k, two_peaks, NARROW, n), 13)
    est_b = run_keys(lambda k: importance(k, two_peaks, BROAD, n), 14)
    v_mis, v_a, v_b = (float(e.mean.var()) for e in (est_mis, est_a, est_b))
    assert v_mis < min(v_a, v_b)
    # Veach's Theorem 9.2: the balance heuristic is within (1/min n_k - 1/sum n_k) I^2 of any
    # other weighting with the same counts, e.g. using only the better technique's n/2 samples.
    better_half = 2 * min(v_a, v_b)
    assert v_mis <= 1.3 * (better_half + (2 / n - 1 / n) * 1.5**2)

    # One peak that the first technique samples exactly (zero variance on its own):
    # MIS cannot match that but stays within Veach's bound.
    f = lambda x: 1.5 * NARROW.pdf(x)
    est = run_keys(lambda k: mis(k, f, [NARROW, BROAD], (n // 2, n // 2)), 15)
    assert float(est.mean.var()) <= 1.3 * (2 / n - 1 / n) * 1.5**2
    assert_unbiased_and_honest(est, 1.5)


def test_mis_bad_inputs(key):
    P = [NARROW, BROAD]
    with pytest.raises(ValueError, match="counts"):
        mis(key, two_peaks, P, (10, 10, 10))
    with pytest.raises(ValueError, match=r"counts\[1\]"):
        mis(key, two_peaks, P, (10, 0))
    with pytest.raises(TypeError, match=r"counts\[0\]"):
        mis(key, two_peaks, P, (10.0, 5))
    with pytest.raises(ValueError, match="heuristic"):
        mis(key, two_peaks, P, 10, heuristic="maximum")
    with pytest.raises(ValueError, match="beta"):
        mis(key, two_peaks, P, 10, heuristic="power", beta=-1.0)
    with pytest.raises(TypeError, match=r"proposals\[1\]"):
        mis(key, two_peaks, [NARROW, "uniform"], 10)
    with pytest.raises(ValueError, match="proposals"):
        mis(key, two_peaks, [], 10)
    with pytest.raises(ValueError, match="probs"):
        mis_one_sample(key, two_peaks, P, jnp.array([0.5, 0.6]), 10)
    with pytest.raises(ValueError, match="probs"):
        mis_one_sample(key, two_peaks, P, jnp.array([1.5, -0.5]), 10)
    with pytest.raises(ValueError, match="probs"):
        mis_one_sample(key, two_peaks, P, jnp.array([1.0]), 10)
    with pytest.raises(ValueError, match="heuristic"):
        mis_one_sample(key, two_peaks, P, jnp.array([0.5, 0.5]), 10, heuristic="Balance")
    with pytest.raises(ValueError, match="`n`"):
        mis_one_sample(key, two_peaks, P, jnp.array([0.5, 0.5]), 0)


# --- control and antithetic variates -------------------------------------------


def test_control_variate_unbiased_honest_and_reduces_variance():
    n = 64
    cv = run_keys(lambda k: control_variate(k, jnp.exp, lambda x: 1 + x, 1.5, 0.0, 1.0, n), 20)
    assert_unbiased_and_honest(cv, np.e - 1)
    plain = run_keys(lambda k: uniform(k, jnp.exp, 0.0, 1.0, n), 21)
    # corr(e^x, x)^2 ≈ 0.984, so the residual variance is ~60x smaller.
    assert cv.mean.var() < plain.mean.var() / 20


def test_control_variate_vector_output_and_odd_n():
    lo, hi = SMOOTH2_LO, SMOOTH2_HI
    g = lambda x: jnp.stack([1 + x[0] - x[1], 1 - 4.5 * (3 * x[0] + x[1] - 2.5) ** 2 / 10])
    G = jnp.array([1.0, 2.0 - 0.45 * 13 / 6])  # E[3x0 + x1 - 2.5] = 0, Var = 13/12
    est = run_keys(lambda k: control_variate(k, smooth2, g, G, lo, hi, 41), 22)
    assert_unbiased_and_honest(est, SMOOTH2)


def test_antithetic_unbiased_honest_and_helps_monotone_f():
    n = 64
    anti = run_keys(lambda k: antithetic(k, jnp.exp, 0.0, 1.0, n), 23)
    assert anti.n[0] == n
    assert_unbiased_and_honest(anti, np.e - 1)
    plain = run_keys(lambda k: uniform(k, jnp.exp, 0.0, 1.0, n), 24)
    assert anti.mean.var() < plain.mean.var() / 10
    lo, hi = SMOOTH2_LO, SMOOTH2_HI
    est = run_keys(lambda k: antithetic(k, smooth2, lo, hi, 50), 25)
    assert_unbiased_and_honest(est, SMOOTH2)


def test_control_and_antithetic_bad_inputs(key):
    with pytest.raises(ValueError, match="`n`"):
        control_variate(key, jnp.exp, jnp.sin, 0.5, 0.0, 1.0, 3)
    with pytest.raises(TypeError, match="`g`"):
        control_variate(key, jnp.exp, 1.0, 0.5, 0.0, 1.0, 10)
    with pytest.raises(ValueError, match="`g`"):
        control_variate(key, jnp.exp, lambda x: jnp.ones(3) * x, 0.5, 0.0, 1.0, 10)
    with pytest.raises(ValueError, match="g_integral"):
        control_variate(key, jnp.exp, jnp.sin, jnp.ones(3), 0.0, 1.0, 10)
    with pytest.raises(ValueError, match="even"):
        antithetic(key, jnp.exp, 0.0, 1.0, 11)
    with pytest.raises(ValueError, match="`lo` must be < `hi`"):
        antithetic(key, jnp.exp, 1.0, 0.0, 10)


# --- jit, vmap over keys and parameters, grad ---------------------------------

LO2, HI2 = SMOOTH2_LO, SMOOTH2_HI

# Each case: (estimator of ∫ f_a, and of ∫ ∂f_a/∂a on the same points), exact d/da ∫ f_a.
# f_a(x) = exp(a x0 - x1) on [0,1]x[0,2] (∫ = (e^a - 1)/a (1 - e^-2)); for MIS,
# f_a(x) = N(x; a, 0.3) whose integral is 1 for every a.


def _strat(fa):
    return lambda key: stratified(key, fa, LO2, HI2, (4, 4))


def _strat1(fa):
    return lambda key: stratified(key, fa, LO2, HI2, (5, 3), per_stratum=1)


def _cv(fa):
    return lambda key: control_variate(key, fa, lambda x: 1 + x[0] - x[1], 1.0, LO2, HI2, 64)


def _anti(fa):
    return lambda key: antithetic(key, fa, LO2, HI2, 64)


BOX_CASES = {"stratified": _strat, "stratified_1": _strat1, "control": _cv, "antithetic": _anti}


@pytest.mark.parametrize("name", sorted(BOX_CASES))
def test_box_estimators_jit_vmap_grad(name, key):
    make = BOX_CASES[name]
    fa, dfa = tilted, tilted_da
    a = 0.7

    jitted = jax.jit(lambda k, a: make(fa(a))(k))(key, a)
    if name == "stratified":  # eager dispatch is slow; one case checks it matches jit
        eager = make(fa(a))(key)
        np.testing.assert_allclose(jitted.mean, eager.mean, rtol=1e-12)
        np.testing.assert_allclose(jitted.variance, eager.variance, rtol=1e-9)
    # vmap over a parameter.
    aa = jnp.array([0.3, 0.7])
    batch = jax.jit(jax.vmap(lambda a: make(fa(a))(key)))(aa)
    np.testing.assert_allclose(batch.mean[1], jitted.mean, rtol=1e-12)
    np.testing.assert_allclose(batch.variance[1], jitted.variance, rtol=1e-9)
    # grad w.r.t. a parameter f closes over: the same estimator applied to ∂f/∂a with
    # the same samples (for the control variate, the cross-fitted c moves with a too,
    # so compare with the exact derivative instead).
    grad = jax.jit(jax.grad(lambda a: make(fa(a))(key).mean))(a)
    exact = tilted_da_integral(a)
    if name != "control":
        np.testing.assert_allclose(grad, jax.jit(make(dfa(a)))(key).mean, rtol=1e-10)
    grads = jax.jit(jax.vmap(jax.grad(lambda a, k: make(fa(a))(k).mean), (None, 0)))(
        a, jax.random.split(key, 200)
    )
    se = np.std(grads) / np.sqrt(200)
    assert abs(np.mean(grads) - exact) < 5 * se + 1e-12, (np.mean(grads), exact)


@pytest.mark.parametrize("model", ["mis", "one_sample"])
def test_mis_jit_vmap_grad(model, key):
    def est(mu, sigma, k):
        P = [Normal(mu, sigma), Normal(1.0, 2.0)]
        f = lambda x: jnp.exp(-0.5 * ((x - 0.5) / 0.3) ** 2)
        if model == "mis":
            return mis(k, f, P, (40, 24), heuristic="power")
        return mis_one_sample(k, f, P, jnp.array([0.6, 0.4]), 64)

    keys = jax.random.split(key, 300)
    jitted = jax.jit(est)(0.4, 0.5, keys[7])
    batch = jax.jit(jax.vmap(est, (None, None, 0)))(0.4, 0.5, keys)
    assert batch.mean.shape == (300,)
    np.testing.assert_allclose(batch.mean[7], jitted.mean, rtol=1e-12)
    np.testing.assert_allclose(batch.variance[7], jitted.variance, rtol=1e-9)
    # The integral 0.3 sqrt(2 pi) does not depend on the proposal: the reparameterised
    # gradient w.r.t. the proposal's parameters has mean zero over keys.
    grads = jax.jit(jax.vmap(jax.grad(lambda m, k: est(m, 0.5, k).mean), (None, 0)))(0.4, keys)
    assert np.all(np.isfinite(grads))
    assert abs(np.mean(grads)) < 5 * np.std(grads) / np.sqrt(300)
    assert_unbiased_and_honest(batch, 0.3 * np.sqrt(2 * np.pi))
