"""Tests of `jaxmc.distributions`: tabulated densities and rejection sampling."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmc.distributions import Piecewise1D, Piecewise2D, disk_rejection, rejection
from jaxmc.testing import chi2_table
from jaxmc.warps import disk_polar_pdf

from .helpers import P_FLOOR


# Bonferroni over the χ² tests of this file (fixed keys: deterministic outcomes).
N_CHI2 = 4
ALPHA = P_FLOOR / N_CHI2

VALUES_1D = jnp.array([0.0, 1.0, 3.0, 0.0, 0.5, 2.0, 2.0, 0.25])
VALUES_2D = jnp.asarray(
    np.random.default_rng(3).gamma(2.0, size=(6, 8)) * (np.arange(8) % 3 != 1)
).at[2].set(0.0)  # a zero column pattern and a zero row


# ---------------------------------------------------------------------------
# Piecewise1D


def test_piecewise1d_tables():
    width = 4.0 / 8
    centers = -1.0 + width * (jnp.arange(8.0) + 0.5)
    edges = -1.0 + width * jnp.arange(9.0)

    @jax.jit
    def tables(values):
        d = Piecewise1D(values, -1.0, 3.0)
        return dict(integral=d.integral, at_centers=d.pdf(centers), at_edges=d.cdf(edges),
                    outside=d.pdf(jnp.array([-1.01, 3.01])), cdf_out=d.cdf(jnp.array([-5.0, 5.0])))

    t = tables(VALUES_1D)
    assert float(t["integral"]) == pytest.approx(float(VALUES_1D.sum()) * width)
    np.testing.assert_allclose(t["at_centers"], VALUES_1D / t["integral"], rtol=1e-12)
    np.testing.assert_array_equal(t["outside"], 0.0)
    np.testing.assert_allclose(
        t["at_edges"], np.concatenate([[0], np.cumsum(VALUES_1D)]) / VALUES_1D.sum(), atol=1e-12)
    np.testing.assert_array_equal(t["cdf_out"], [0.0, 1.0])


def test_piecewise1d_sample_inverts_cdf(key):
    d = Piecewise1D(VALUES_1D, -1.0, 3.0)
    u = jax.random.uniform(key, (1000,))
    edge_u = jnp.array([0.0, 1.0 / 9, 0.999999])  # on the CDF's flat steps and ends

    @jax.jit
    def check(d, u):
        x, p = d.sample(u)
        x0, p0 = d.sample(edge_u)
        return x, p, d.cdf(x), d.pdf(x), p0, d.sample(u[0])

    x, p, cdf, pdf, p0, (xs, ps) = check(d, u)
    assert x.shape == p.shape == (1000,)
    np.testing.assert_allclose(cdf, u, atol=1e-12)
    np.testing.assert_allclose(p, pdf, rtol=1e-12)
    # Zero-valued cells are never sampled, even at the CDF's flat steps.
    assert jnp.all(p > 0) and jnp.all(p0 > 0)
    # A scalar u gives a scalar.
    assert xs.shape == () and ps.shape == ()


def test_piecewise1d_chi2():
    d = Piecewise1D(VALUES_1D, -1.0, 3.0)

    def sample(key, n):
        return d.sample(jax.random.uniform(key, (n,)))[0]

    # 64 bins: 8 per tabulated cell, so the density's jumps are on bin edges.
    table = chi2_table(jax.random.key(11), sample, d.pdf, (-1.0, 3.0), n=100_000, bins=64)
    assert table.p_value > ALPHA, table.report()


def test_piecewise1d_grad_through_sample():
    # The sample moves with the tabulated CDF: compare with central differences.
    u = jnp.array([0.05, 0.45, 0.8])  # away from the CDF knots 0.1, 0.3, 0.6
    values = jnp.array([1.0, 2.0, 3.0, 4.0])

    def f(v):
        return jnp.sum(jnp.sin(3 * Piecewise1D(v).sample(u)[0]))

    g = jax.jit(jax.grad(f))(values)
    h = 1e-6
    for i in range(4):
        e = jnp.zeros(4).at[i].set(h)
        assert float(g[i]) == pytest.approx(float((f(values + e) - f(values - e)) / (2 * h)),
                                            rel=1e-5, abs=1e-9)


def test_piecewise1d_vmap_over_tables():
    tables = jnp.stack([VALUES_1D, VALUES_1D[::-1], jnp.ones(8)])
    x, p = jax.jit(jax.vmap(lambda v: Piecewise1D(v).sample(jnp.array([0.3, 0.7]))))(tables)
    assert x.shape == (3, 2)
    np.testing.assert_allclose(x[2], [0.3, 0.7], atol=1e-12)  # uniform table: identity


@pytest.mark.parametrize(
    "values, lo, hi, match",
    [
        ([1.0, -0.5], 0.0, 1.0, "`values`"),
        ([0.0, 0.0], 0.0, 1.0, "`values`"),
        ([1.0, np.nan], 0.0, 1.0, "`values`"),
        ([[1.0, 2.0]], 0.0, 1.0, "`values`"),
        ([], 0.0, 1.0, "`values`"),
        ([1.0, 2.0], 1.0, 0.0, "`lo`"),
        ([1.0, 2.0], jnp.zeros(2), jnp.ones(2), "`lo`"),
    ],
)
def test_piecewise1d_bad_input(values, lo, hi, match):
    with pytest.raises(ValueError, match=match):
        Piecewise1D(jnp.asarray(values), lo, hi)


# ---------------------------------------------------------------------------
# Piecewise2D

LO, HI = jnp.array([0.0, -1.0]), jnp.array([2.0, 2.0])


def test_piecewise2d_tables(key):
    dx, dy = 2.0 / 8, 3.0 / 6
    xc = LO[0] + dx * (jnp.arange(8.0) + 0.5)
    yc = LO[1] + dy * (jnp.arange(6.0) + 0.5)
    grid = jnp.stack(jnp.meshgrid(xc, yc, indexing="xy"), axis=-1)  # (ny, nx, 2), row = y
    u = jax.random.uniform(key, (2000, 2))

    @jax.jit
    def tables(values):
        d = Piecewise2D(values, LO, HI)
        xy, p = d.sample(u)
        return dict(integral=d.integral, at_centers=d.pdf(grid),
                    outside=d.pdf(jnp.array([2.5, 0.0])), xy=xy, p=p, pdf=d.pdf(xy))

    t = tables(VALUES_2D)
    assert float(t["integral"]) == pytest.approx(float(VALUES_2D.sum()) * dx * dy)
    np.testing.assert_allclose(t["at_centers"], VALUES_2D / t["integral"], rtol=1e-12)
    assert float(t["outside"]) == 0.0
    xy, p = t["xy"], t["p"]
    assert xy.shape == (2000, 2) and p.shape == (2000,)
    np.testing.assert_allclose(p, t["pdf"], rtol=1e-12)
    assert jnp.all(p > 0)  # zero rows and cells are never sampled
    assert np.all((np.asarray(xy) >= np.asarray(LO)) & (np.asarray(xy) <= np.asarray(HI)))


def test_piecewise2d_chi2():
    d = Piecewise2D(VALUES_2D, LO, HI)

    def sample(key, n):
        return d.sample(jax.random.uniform(key, (n, 2)))[0]

    # bins (x, y) = (16, 12): two per tabulated cell on each axis.
    table = chi2_table(jax.random.key(12), sample, d.pdf, ((0.0, -1.0), (2.0, 2.0)),
                       n=100_000, bins=(16, 12))
    assert table.p_value > ALPHA, table.report()


def test_piecewise2d_image_orientation():
    # One bright pixel in row 1 (y), column 3 (x): samples land in that pixel.
    img = jnp.zeros((4, 5)).at[1, 3].set(1.0)
    xy, p = jax.jit(lambda v: Piecewise2D(v).sample(jnp.array([[0.2, 0.7], [0.9, 0.1]])))(img)
    assert jnp.all((xy[:, 0] >= 3 / 5) & (xy[:, 0] <= 4 / 5))
    assert jnp.all((xy[:, 1] >= 1 / 4) & (xy[:, 1] <= 2 / 4))
    np.testing.assert_allclose(p, 20.0)


def test_piecewise2d_bad_input():
    with pytest.raises(ValueError, match="`values`"):
        Piecewise2D(jnp.ones(5))
    with pytest.raises(ValueError, match="`values`"):
        Piecewise2D(-jnp.ones((2, 2)))
    with pytest.raises(ValueError, match="`values`"):
        Piecewise2D(jnp.zeros((2, 2)))
    with pytest.raises(ValueError, match="`lo`"):
        Piecewise2D(jnp.ones((2, 2)), 0.0, 1.0)
    with pytest.raises(ValueError, match="`u`"):
        Piecewise2D(jnp.ones((2, 2))).sample(jnp.zeros(3))


# ---------------------------------------------------------------------------
# rejection


def test_disk_rejection_acceptance_rate(key):
    # One round of exactly n proposals: the rate is accepted / n, efficiency pi/4 (lecture §3.2).
    n = 20_000
    x, mask, rate = rejection(
        key, n, lambda k, m: jax.random.uniform(k, (m, 2), minval=-1.0, maxval=1.0),
        lambda k, x: jnp.sum(x * x, -1) < 1.0, max_rounds=1)
    assert float(rate) == pytest.approx(float(mask.mean()))
    sigma = math.sqrt(math.pi / 4 * (1 - math.pi / 4) / n)
    assert abs(float(rate) - math.pi / 4) < 5 * sigma
    # With enough rounds every slot is filled; the rate counts every proposal.
    x, mask, rate = jax.jit(lambda k: disk_rejection(k, n))(key)
    assert bool(mask.all())
    assert abs(float(rate) - math.pi / 4) < 5 * sigma
    assert jnp.all(jnp.sum(x * x, -1) < 1.0)


def test_disk_rejection_chi2():
    def sample(key, n):
        return disk_rejection(key, n)[0]

    table = chi2_table(jax.random.key(13), sample, disk_polar_pdf, "disk", n=50_000, bins=16)
    assert table.p_value > ALPHA, table.report()


def test_rejection_with_probabilistic_acceptance():
    # Target 2x on [0, 1] from uniform proposals, accepting with probability x (efficiency 1/2).
    def propose(k, m):
        return jax.random.uniform(k, (m,))

    def accept(k, x):
        return jax.random.uniform(k, x.shape) < x

    def sample(key, n):
        return rejection(key, n, propose, accept)[0]

    table = chi2_table(jax.random.key(14), sample, lambda x: 2 * x, (0.0, 1.0), n=50_000,
                       bins=20)
    assert table.p_value > ALPHA, table.report()


def test_rejection_fills_slots_in_order_with_stubs(key):
    # Deterministic stubs in place of the random parts.
    def propose(k, m):
        return jnp.arange(m, dtype=float)

    x, mask, rate = rejection(key, 10, propose, lambda k, x: x % 3 == 0, max_rounds=2)
    np.testing.assert_array_equal(x, [0, 3, 6, 9, 0, 3, 6, 9, 0, 0])
    np.testing.assert_array_equal(mask, [True] * 8 + [False] * 2)
    assert float(rate) == pytest.approx(8 / 20)

    x, mask, rate = rejection(key, 4, propose, lambda k, x: x >= 0, batch_size=6)
    np.testing.assert_array_equal(x, [0, 1, 2, 3])
    assert bool(mask.all()) and float(rate) == 1.0  # overflowing acceptances still count

    x, mask, rate = rejection(key, 4, propose, lambda k, x: x < 0, max_rounds=3)
    assert not bool(mask.any()) and float(rate) == 0.0
    np.testing.assert_array_equal(x, 0.0)

    # Stops as soon as the slots are full: 1 round here, so 4 proposals.
    x, mask, rate = rejection(key, 4, propose, lambda k, x: x < 2, batch_size=4, max_rounds=5)
    np.testing.assert_array_equal(x, [0, 1, 0, 1])
    assert float(rate) == pytest.approx(4 / 8)


def test_rejection_bad_input(key):
    good_propose = lambda k, m: jax.random.uniform(k, (m, 2))
    good_accept = lambda k, x: x[:, 0] < 0.5
    with pytest.raises(ValueError, match="`propose"):
        rejection(key, 5, lambda k, m: jnp.zeros((3, 2)), good_accept)
    with pytest.raises(ValueError, match="`accept"):
        rejection(key, 5, good_propose, lambda k, x: x < 0.5)
    with pytest.raises(TypeError, match="`accept"):
        rejection(key, 5, good_propose, lambda k, x: x[:, 0])
    with pytest.raises(ValueError, match="`n`"):
        rejection(key, 0, good_propose, good_accept)
    with pytest.raises(ValueError, match="`max_rounds`"):
        rejection(key, 5, good_propose, good_accept, max_rounds=0)
    with pytest.raises(TypeError, match="`key`"):
        disk_rejection(jnp.zeros(3), 5)
