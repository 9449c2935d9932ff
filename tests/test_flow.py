"""Tests of `Flow`, the rational-quadratic spline coupling flow on a box."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
import pytest
import scipy.stats

import jaxmc
import jaxmc.fit
from jaxmc._fit._solvers import default_solver
from jaxmc._proposals._flow import _rqs_forward, _rqs_inverse
from jaxmc.proposals import Flow

from .helpers import importance, midpoint_grid


LO2 = jnp.array([-1.0, 0.0])
HI2 = jnp.array([2.0, 0.5])


def _perturbed(key, lo=LO2, hi=HI2, scale=3.0, layers=2, hidden=16):
    # init_scale well above the default: a clearly non-uniform density. Small
    # networks and few layers keep compilation short; the default layer count
    # (binary masks) is exercised by the d = 3 case of test_sample_pdf_matches_log_pdf.
    return Flow(key, lo, hi, init_scale=scale, layers=layers, hidden=hidden)


@pytest.fixture(scope="module")
def flow2():
    """A clearly non-uniform 2-D flow on a non-unit box, shared to save compilations."""
    return _perturbed(jax.random.key(20261122))


def test_zero_init_is_uniform(key):
    flow = _perturbed(key, scale=0.0)
    u = jax.random.uniform(jax.random.key(1), (512, 2))
    x, log_p = flow.forward(u)
    np.testing.assert_allclose(x, LO2 + (HI2 - LO2) * u, rtol=0, atol=1e-12)
    np.testing.assert_allclose(log_p, -np.log(1.5), rtol=1e-12)
    np.testing.assert_allclose(flow.pdf(x), 1 / 1.5, rtol=1e-12)


def test_integrates_to_one_2d(flow2):
    flow = flow2
    pts, area = midpoint_grid(LO2, HI2, 600)
    pdf = flow.pdf(pts)
    # The density really varies (so a wrong log-det could not pass by luck)...
    assert float(pdf.max() / pdf.min()) > 20
    # ...and its midpoint integral is 1 to the rule's accuracy (~2e-5 at m=600).
    assert abs(float(jnp.sum(pdf) * area) - 1.0) < 1e-4


def test_integrates_to_one_1d_scalar_bounds(key):
    flow = Flow(key, 0.0, 2.0, init_scale=0.5)
    m = 100_000
    x = 2.0 * (jnp.arange(m) + 0.5) / m
    pdf = flow.pdf(x)
    assert pdf.shape == (m,)
    assert float(pdf.max() / pdf.min()) > 20
    assert abs(float(jnp.mean(pdf) * 2.0) - 1.0) < 1e-5


@pytest.mark.parametrize("d", [1, 3])
def test_sample_pdf_matches_log_pdf(key, d):
    flow = _perturbed(key, jnp.zeros(d), jnp.full(d, 2.0), scale=1.0, layers=None)
    assert len(flow.layers) == (2 if d == 1 else 4)
    x, pdf = flow.sample(jax.random.key(1), 512)
    assert x.shape == (512, d) and pdf.shape == (512,)
    assert bool(jnp.all((x >= 0) & (x <= 2)))
    np.testing.assert_allclose(flow.pdf(x), pdf, rtol=1e-9)
    # One point at a time gives the same.
    np.testing.assert_allclose(flow.log_pdf(x[3]), jnp.log(pdf[3]), rtol=1e-9)


def test_float32(key):
    lo, hi = jnp.zeros(3, jnp.float32), jnp.full(3, 4.0, jnp.float32)
    flow = _perturbed(key, lo, hi, scale=1.0, layers=3)
    x, pdf = flow.sample(jax.random.key(1), 512)
    assert x.dtype == jnp.float32 and pdf.dtype == jnp.float32
    assert bool(jnp.all((x >= lo) & (x <= hi)))
    assert bool(jnp.all(jnp.isfinite(pdf) & (pdf > 0)))
    np.testing.assert_allclose(flow.pdf(x), pdf, rtol=1e-4)
    u, _ = flow.inverse(x)
    assert bool(jnp.all(jnp.isfinite(u)))


def test_inverse_of_forward(key):
    flow = _perturbed(key, jnp.zeros(3), jnp.ones(3), scale=1.0, layers=3)
    u = jax.random.uniform(jax.random.key(1), (509, 3))
    # Include the faces of the cube and points next to them.
    edges = jnp.array([[0.0, 1.0, 1e-12], [1.0, 0.0, 1 - 1e-12], [0.5, 1e-9, 1.0]])
    u = jnp.concatenate([u, edges])
    x, log_p = flow.forward(u)
    u_back, log_p_back = flow.inverse(x)
    np.testing.assert_allclose(u_back, u, rtol=0, atol=1e-9)
    np.testing.assert_allclose(log_p_back, log_p, rtol=0, atol=1e-7)
    assert bool(jnp.all(jnp.isfinite(log_p)))


def test_spline_is_monotone_and_inverse_exact():
    bins = 8
    raw = 2.0 * jax.random.normal(jax.random.key(3), (3 * bins + 1,))
    x = jnp.linspace(0.0, 1.0, 2001)
    y, log_det = jax.vmap(_rqs_forward, in_axes=(0, None, None))(x, raw, bins)
    assert float(y[0]) == 0.0 and float(y[-1]) == 1.0
    assert bool(jnp.all(jnp.diff(y) > 0))
    # log-det is the log of the map's derivative.
    dlog = jax.vmap(jax.grad(lambda t: _rqs_forward(t, raw, bins)[0]))(x)
    np.testing.assert_allclose(jnp.log(dlog), log_det, rtol=1e-9, atol=1e-9)
    x_back, inv_log_det = jax.vmap(_rqs_inverse, in_axes=(0, None, None))(y, raw, bins)
    np.testing.assert_allclose(x_back, x, atol=1e-12)
    np.testing.assert_allclose(inv_log_det, -log_det, atol=1e-9)


def test_outside_box_and_shapes(key, flow2):
    flow = flow2
    outside = jnp.array([[-1.5, 0.2], [0.0, 0.6], [2.0 + 1e-9, 0.1]])
    assert bool(jnp.all(flow.log_pdf(outside) == -jnp.inf))
    assert bool(jnp.all(flow.pdf(outside) == 0))
    # Arbitrary batch shapes.
    pts = jnp.full((4, 5, 2), 0.25)
    assert flow.log_pdf(pts).shape == (4, 5)
    assert flow.log_pdf(pts[0, 0]).shape == ()
    with pytest.raises(ValueError, match="`x` must have shape"):
        flow.log_pdf(jnp.zeros((4, 3)))

    scalar = Flow(key, -1.0, 1.0, init_scale=0.5)
    assert scalar.event_ndim == 0 and scalar.dim == 1
    x, pdf = scalar.sample(jax.random.key(1), 100)
    assert x.shape == (100,) and pdf.shape == (100,)
    np.testing.assert_allclose(scalar.pdf(x), pdf, rtol=1e-9)
    assert scalar.log_pdf(x[0]).shape == ()
    assert float(scalar.pdf(1.5)) == 0.0


def test_bad_arguments(key):
    with pytest.raises(ValueError, match="`layers`"):
        Flow(key, LO2, HI2, layers=0)
    with pytest.raises(ValueError, match="`bins`"):
        Flow(key, LO2, HI2, bins=1)
    with pytest.raises(ValueError, match="`lo` must be < `hi`"):
        Flow(key, HI2, LO2)
    with pytest.raises(TypeError, match="`key`"):
        Flow(0, LO2, HI2)
    with pytest.raises(TypeError, match="`n`"):
        _perturbed(key).sample(key, 10.0)


def test_chi2_samples_follow_pdf(flow2):
    """Histogram of samples on a 10 x 10 grid vs the pdf integrated on the cells."""
    flow = flow2
    n, cells, sub = 40_000, 10, 60
    x, _ = flow.sample(jax.random.key(7), n)
    pts, area = midpoint_grid(LO2, HI2, cells * sub)
    mass = np.asarray(flow.pdf(pts)).reshape(cells, sub, cells, sub).sum(axis=(1, 3)) * area
    expected = n * mass.ravel() / mass.sum()
    scaled = np.asarray((x - LO2) / (HI2 - LO2))
    observed, _, _ = np.histogram2d(scaled[:, 0], scaled[:, 1], bins=cells, range=[[0, 1], [0, 1]])
    observed = observed.ravel()
    assert expected.min() > 5, expected.min()
    stat = np.sum((observed - expected) ** 2 / expected)
    p = scipy.stats.chi2.sf(stat, cells * cells - 1)
    assert p > 1e-4, (p, np.c_[expected, observed])
    # The test has power: the same samples are far from uniform.
    uniform = np.full(cells * cells, n / cells**2)
    stat_u = np.sum((observed - uniform) ** 2 / uniform)
    assert scipy.stats.chi2.sf(stat_u, cells * cells - 1) < 1e-10


def test_ks_samples_follow_pdf_1d(key):
    flow = Flow(key, 0.0, 1.0, init_scale=0.5)
    m = 200_000
    grid = jnp.linspace(0.0, 1.0, m + 1)
    pdf = np.asarray(flow.pdf(grid))
    cdf = np.concatenate([[0.0], np.cumsum((pdf[1:] + pdf[:-1]) / 2) / m])
    assert abs(cdf[-1] - 1) < 1e-6
    x, _ = flow.sample(jax.random.key(11), 5000)
    cdf_fn = lambda t: np.interp(t, np.asarray(grid), cdf)
    assert scipy.stats.kstest(np.asarray(x), cdf_fn).pvalue > 1e-4
    assert scipy.stats.kstest(np.asarray(x), "uniform").pvalue < 1e-6


def test_grad_log_pdf_finite_and_correct(flow2):
    flow = flow2
    x = jax.random.uniform(jax.random.key(1), (512, 2)) * (HI2 - LO2) + LO2
    params, static = eqx.partition(flow, jaxmc.fit.parameter_spec(flow))
    loss = lambda p: jnp.mean(eqx.combine(p, static).log_pdf(x))
    grads = jax.jit(jax.grad(loss))(params)
    leaves = jax.tree_util.tree_leaves(grads)
    assert leaves and all(bool(jnp.all(jnp.isfinite(g))) for g in leaves)
    assert any(float(jnp.max(jnp.abs(g))) > 0 for g in leaves)
    # Directional derivative against float64 central differences.
    direction = jax.tree_util.tree_map(
        lambda g: jax.random.normal(jax.random.key(2), g.shape, g.dtype), grads
    )
    h = 1e-6
    shift = lambda s: jax.tree_util.tree_map(lambda p, v: p + s * v, params, direction)
    fd = (loss(shift(h)) - loss(shift(-h))) / (2 * h)
    exact = sum(jnp.vdot(g, v) for g, v in zip(leaves, jax.tree_util.tree_leaves(direction)))
    np.testing.assert_allclose(exact, fd, rtol=1e-5)


def test_reparameterised_sample_gradient(flow2):
    flow = flow2
    params, static = eqx.partition(flow, jaxmc.fit.parameter_spec(flow))

    def loss(p):
        x, pdf = eqx.combine(p, static).sample(jax.random.key(5), 512)
        return jnp.mean(x**2) + jnp.mean(jnp.log(pdf))

    grads = jax.jit(jax.grad(loss))(params)
    leaves = jax.tree_util.tree_leaves(grads)
    assert all(bool(jnp.all(jnp.isfinite(g))) for g in leaves)
    assert any(float(jnp.max(jnp.abs(g))) > 0 for g in leaves)


def test_jit_and_vmap(flow2):
    flow = flow2
    k = jax.random.key(3)
    x, pdf = flow.sample(k, 512)
    x_jit, pdf_jit = eqx.filter_jit(lambda fl, kk: fl.sample(kk, 512))(flow, k)
    np.testing.assert_allclose(x_jit, x, rtol=1e-12)
    np.testing.assert_allclose(pdf_jit, pdf, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(
        eqx.filter_jit(lambda fl, y: fl.log_pdf(y))(flow, x[0]), jnp.log(pdf[0]), rtol=1e-10, atol=1e-12
    )
    keys = jax.random.split(jax.random.key(4), 3)
    xs, pdfs = jax.vmap(lambda kk: flow.sample(kk, 512))(keys)
    assert xs.shape == (3, 512, 2) and pdfs.shape == (3, 512)
    x1, _ = flow.sample(keys[1], 512)
    np.testing.assert_allclose(xs[1], x1, rtol=1e-12)
    # vmap over points of the one-point log_pdf.
    np.testing.assert_allclose(jax.vmap(flow.log_pdf)(x), jnp.log(pdf), rtol=1e-10, atol=1e-12)
    # Legacy keys work.
    x2, _ = flow.sample(jax.random.PRNGKey(3), 512)
    assert x2.shape == (512, 2)


def _camel(alpha):
    """Two Gaussians on the diagonal of [0,1]^2, normalised to 1 on the plane."""
    norm = (alpha * jnp.sqrt(jnp.pi)) ** 2

    def f(x):
        a = jnp.exp(-jnp.sum((x - 1 / 3) ** 2) / alpha**2)
        b = jnp.exp(-jnp.sum((x - 2 / 3) ** 2) / alpha**2)
        return 0.5 * (a + b) / norm

    return f


def test_fit_camel_reduces_variance(key):
    """`fit`'s default for a flow: VEGAS rounds find the camel's modes, then Adam minimises
    the forward KL to |f|/I on a fresh batch from the grid each step; the variance per
    evaluation must drop >= 10x."""
    f = _camel(0.1)
    lo, hi = jnp.zeros(2), jnp.ones(2)
    # A small flow and budget to keep the test quick.
    flow = Flow(key, lo, hi, layers=2, hidden=32)
    # The default initialisation is close to uniform.
    _, pdf0 = flow.sample(jax.random.key(4), 512)
    np.testing.assert_allclose(pdf0, 1.0, rtol=0.1)
    res = jaxmc.fit.fit(jax.random.key(1), f, flow, 512, max_steps=150)
    assert res.losses.shape == (150,)  # one loss per step: a fresh batch at every step
    fitted = res.proposal
    assert isinstance(fitted, Flow)
    np.testing.assert_array_equal(fitted.lo, lo)  # the box is not a parameter
    losses = np.asarray(res.losses)
    assert np.all(np.isfinite(losses))
    # The divergence from the near-uniform start is -H(p_f) ~ 1.77 nats; it ends near 0.
    assert losses[0] > 1.5 and losses[-20:].mean() < losses[0] - 1.0, (losses[0], losses[-20:])

    n = 2**16
    est_flow = importance(jax.random.key(2), f, fitted, n)
    est_unif = importance(jax.random.key(3), f, jaxmc.proposals.Uniform(lo, hi), n)
    # The integral over the unit square is 1 up to ~1e-10 of Gaussian tails.
    for est in (est_flow, est_unif):
        assert abs(float(est.mean) - 1.0) < 4 * float(est.stderr)
        assert int(est.n_nonfinite) == 0
    ratio = float(est_unif.variance / est_flow.variance)
    assert ratio >= 10.0, ratio


def test_fit_default_solver_for_flows(key):
    """A flow's default fit: VEGAS rounds, then Adam on the forward KL for exactly
    `max_steps` steps. Its gradient fit (any other objective) defaults to Adam on fresh
    samples for exactly `max_steps` steps; other proposals' to BFGS on fixed samples."""
    f = _camel(0.2)
    lo, hi = jnp.zeros(2), jnp.ones(2)
    flow = Flow(key, lo, hi, layers=2, hidden=8)
    adam = optx.OptaxMinimiser(optax.adam(3e-3), rtol=0.0, atol=0.0)
    fit = lambda prop, **kw: jaxmc.fit.fit(jax.random.key(1), f, prop, 128, max_steps=6, **kw)
    default = fit(flow)
    assert default.losses.shape == (6,) and int(default.steps) == 6 + 6  # rounds + steps
    gradient, explicit = fit(flow, objective="chi2"), fit(
        flow, objective="chi2", solver=adam, resample=True
    )
    assert gradient.losses.shape == (6,) and int(gradient.steps) == 6
    np.testing.assert_array_equal(gradient.losses, explicit.losses)
    # One reused batch: no fresh samples, so no per-step losses.
    assert fit(flow, reuse=True).losses is None
    # (Each fit compiles anew, so the other cases check the choice, not a run.)
    mixed = jaxmc.proposals.Mixture((flow, jaxmc.proposals.Uniform(lo, hi)), jnp.array([0.9, 0.1]))
    params = lambda prop: eqx.filter(prop, eqx.is_inexact_array)
    assert isinstance(default_solver(mixed, params(mixed)), optx.OptaxMinimiser)
    gm = jaxmc.proposals.GaussianMixture(jax.random.key(2), lo, hi, 2)
    assert isinstance(default_solver(gm, params(gm)), optx.BFGS)
