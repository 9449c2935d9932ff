"""Fitted-proposal densities: normalisation, sampling law, gradients, refinement, errors."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats as sps

from jaxmc.fit import adapt
from jaxmc.proposals import (
    GaussianMixture,
    Grid,
    Mixture,
    Partition,
    PiecewiseLinear,
    Uniform,
)


LO2, HI2 = jnp.array([0.0, -1.0]), jnp.array([1.0, 2.0])

# Jitted entry points: eager op-by-op dispatch of the samplers is what makes a test slow.
sample = eqx.filter_jit(lambda q, key, n: q.sample(key, n))
pdf = eqx.filter_jit(lambda q, x: q.pdf(x))
pdf_log = eqx.filter_jit(lambda q, x: q.log_pdf(x))
from_samples = eqx.filter_jit(GaussianMixture.from_samples)  # (its EM loops, eagerly, op by op)


def _quad_2d(pdf, lo, hi, m=400):
    """Midpoint rule on an m x m grid (the Grid's edges need not align: error O(1/m))."""
    t = (jnp.arange(m) + 0.5) / m
    xs = lo[0] + (hi[0] - lo[0]) * t
    ys = lo[1] + (hi[1] - lo[1]) * t
    pts = jnp.stack(jnp.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
    return jnp.sum(pdf(pts)) * jnp.prod(hi - lo) / m**2


def _random_grid(key, lo, hi, bins):
    g = Grid(lo, hi, bins)
    return eqx.tree_at(lambda g: g.logits, g, 0.4 * jax.random.normal(key, g.logits.shape))


def _random_linear(key, lo, hi, bins):
    p = PiecewiseLinear(lo, hi, bins)
    return eqx.tree_at(lambda q: q.log_heights, p, jax.random.normal(key, p.log_heights.shape))


@eqx.filter_jit
def _grown_partition(key, lo, hi, cells=64):
    """A partition grown by `adapt` on an off-centre peak, then given random cell masses."""
    c = lo + 0.3 * (hi - lo)
    f = lambda x: jnp.exp(-20.0 * jnp.sum((x - c) ** 2))
    _, part = adapt(key, f, Partition(lo, hi, cells), iterations=3, n_per_iteration=4 * cells)
    return eqx.tree_at(lambda p: p.logits, part, jax.random.normal(key, part.logits.shape))


def _proposals(key):
    k1, k2, k3 = jax.random.split(key, 3)
    gm = GaussianMixture(k1, LO2, HI2, components=3)
    # Off-centre, narrow and wide components so truncation matters.
    gm = eqx.tree_at(
        lambda g: (g.means, g.log_scales, g.logits),
        gm,
        (
            jnp.array([[0.9, 1.8], [0.1, -0.5], [2.0, 0.0]]),
            jnp.log(jnp.array([[0.05, 0.3], [0.4, 1.0], [0.3, 0.2]])),
            jnp.array([0.0, 1.0, -1.0]),
        ),
    )
    grid = _random_grid(k2, LO2, HI2, 16)
    mix = Mixture((gm, grid, Uniform(LO2, HI2)), (0.5, 0.3, 0.2))
    linear = _random_linear(k3, LO2, HI2, 5)
    partition = _grown_partition(jax.random.fold_in(key, 4), LO2, HI2)
    assert int(partition.n_cells) > 32  # the peak made it grow
    return {"gm": gm, "grid": grid, "mix": mix, "linear": linear, "partition": partition}


@pytest.mark.parametrize("name", ["gm", "grid", "mix", "linear", "partition"])
def test_normalised_and_consistent(key, name):
    prop = _proposals(key)[name]
    total = _quad_2d(lambda x: pdf(prop, x), LO2, HI2, m=600)
    assert abs(float(total) - 1.0) < 5e-3, total
    x, p = sample(prop, jax.random.fold_in(key, 1), 4000)
    assert x.shape == (4000, 2) and p.shape == (4000,)
    assert bool(jnp.all((x >= LO2) & (x <= HI2)))
    np.testing.assert_allclose(p, pdf(prop, x), rtol=1e-9)
    np.testing.assert_allclose(jnp.exp(prop.log_pdf(x[0])), p[0], rtol=1e-9)
    # Outside the box the density is zero.
    assert float(prop.pdf(jnp.array([1.5, 0.0]))) == 0.0
    # Unbiased: E_p[1/p] is the box volume (3).
    est = jnp.mean(1.0 / p)
    se = jnp.std(1.0 / p) / jnp.sqrt(4000.0)
    assert abs(float(est) - 3.0) < 5 * float(se) + 1e-9


def test_stratified_mixture_draws_its_shares(key):
    """`Mixture(..., stratified=True)`: n w_k points from component k (largest remainders),
    each with its density under the mixture of the realised shares: an unbiased estimate."""
    gm = GaussianMixture(jax.random.fold_in(key, 5), LO2, HI2, components=3)
    parts = (gm, _random_grid(jax.random.fold_in(key, 6), LO2, HI2, 16), Uniform(LO2, HI2))
    weights = (0.5, 0.3, 0.2)
    mix = Mixture(parts, weights, stratified=True)
    assert mix.counts(1000) == (500, 300, 200) and mix.counts(7) == (4, 2, 1)  # 3.5, 2.1, 1.4
    x, p = sample(mix, key, 7)
    shares = jnp.asarray(mix.counts(7)) / 7
    expected = sum(s * pdf(q, x) for s, q in zip(shares, parts))
    np.testing.assert_allclose(p, expected, rtol=1e-6)
    # The four points of the Gaussian mixture, turned by the random offset with the others.
    gm_points = sample(gm, jax.random.split(key, 4)[1], 4)[0]
    assert sum(bool(jnp.any(jnp.all(x == g, axis=-1))) for g in gm_points) == 4
    # Unbiased for the integral of a peaked f over many keys (within 5 standard errors).
    f = lambda x: jnp.exp(-20.0 * jnp.sum((x - jnp.array([0.3, 0.0])) ** 2, axis=-1))  # noqa: E731
    exact = float(_quad_2d(f, LO2, HI2, m=1000))

    @eqx.filter_jit
    def estimates(q, keys):
        def one(k):
            x, p = q.sample(k, 64)
            y = f(x) / p
            return jnp.mean(y), jnp.mean(y[:20])
        return jax.vmap(one)(keys)

    # All 64 points, and the first 20 (as a stream's last, partly used block keeps them),
    # of the same draws (one compiled program).
    both = estimates(mix, jax.random.split(jax.random.fold_in(key, 2), 4000))
    for m, strat in zip((64, 20), both, strict=True):
        se = float(jnp.std(strat)) / np.sqrt(strat.shape[0])
        assert abs(float(jnp.mean(strat)) - exact) < 5 * se, (m, float(jnp.mean(strat)), exact, se)
    with pytest.raises(ValueError, match="stratified"):
        Mixture(parts, weights, stratified=True, train_weights=True)
    with pytest.raises(ValueError, match="stratified"):
        Mixture(parts, weights).counts(10)
    with pytest.raises(ValueError, match="stratified"):  # traced weights: counts unknown
        jax.jit(lambda w: Mixture(parts[:2], [w, 1 - w], stratified=True).log_weights)(0.5)


@pytest.mark.parametrize("name", ["gm", "grid", "linear", "partition"])
def test_sampling_law_1d(key, name):
    """Binned chi-square of 1-D samples against the pdf integrated per bin."""
    if name == "gm":
        prop = GaussianMixture(key, -1.0, 2.0, components=2)
        prop = eqx.tree_at(
            lambda g: (g.means, g.log_scales),
            prop,
            (jnp.array([[1.8], [-3.0]]), jnp.log(jnp.array([[0.2], [1.5]]))),
        )
    elif name == "grid":
        prop = _random_grid(key, -1.0, 2.0, 12)
    elif name == "partition":
        prop = _grown_partition(key, -1.0, 2.0, cells=16)
    else:
        prop = _random_linear(key, -1.0, 2.0, 7)
    n, bins = 40_000, 30
    x, _ = sample(prop, jax.random.fold_in(key, 7), n)
    assert x.shape == (n,)
    edges = np.linspace(-1.0, 2.0, bins + 1)
    fine = jnp.linspace(-1.0, 2.0, bins * 200 + 1)
    mids = 0.5 * (fine[1:] + fine[:-1])
    mass = np.asarray(pdf(prop, mids)).reshape(bins, 200).sum(axis=1) * (3.0 / (bins * 200))
    counts, _ = np.histogram(np.asarray(x), edges)
    expected = n * mass / mass.sum()
    stat = np.sum((counts - expected) ** 2 / expected)
    p_value = sps.chi2.sf(stat, bins - 1)
    assert p_value > 1e-3, (counts, expected.round(1))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("offset", [0.0, 1000.0])
def test_gaussian_mixture_density_matches_scipy(dtype, offset):
    """The mixture of truncated normals' log density against SciPy's, with narrow (1e-3)
    and wide components, on a box far from the origin too (float64 sums its quadratic
    forms as matrix products about the box's centre; float32 point by point)."""
    as_dtype = lambda a: np.asarray(jnp.asarray(a, dtype), np.float64)  # the values it holds
    lo, hi = as_dtype(np.array([0.0, -1.0]) + offset), as_dtype(np.array([1.0, 2.0]) + offset)
    means = as_dtype(np.array([[0.4, 0.5], [0.9, 1.8], [0.2, -0.9]]) + offset)
    log_scales = as_dtype(np.log([[1e-3, 2e-3], [0.05, 0.3], [0.4, 1.0]]))
    logits = np.array([0.0, 1.0, -1.0])
    g = GaussianMixture(jax.random.key(0), jnp.asarray(lo, dtype), jnp.asarray(hi, dtype), 3)
    g = eqx.tree_at(lambda m: (m.means, m.log_scales, m.logits), g,
                    tuple(jnp.asarray(a, dtype) for a in (means, log_scales, logits)))
    scales = np.exp(log_scales)
    rng = np.random.default_rng(0)
    # Points near each component's mean (within a few scales) and across the box.
    x = np.concatenate([means[k] + scales[k] * rng.normal(size=(50, 2)) for k in range(3)]
                       + [lo + (hi - lo) * rng.uniform(size=(50, 2))])
    x = as_dtype(np.clip(x, lo, hi))
    a, b = (lo - means) / scales, (hi - means) / scales
    parts = [np.sum(sps.truncnorm.logpdf(x, a[k], b[k], means[k], scales[k]), axis=-1)
             for k in range(3)]
    w = np.exp(logits) / np.sum(np.exp(logits))
    expected = np.log(sum(wk * np.exp(pk) for wk, pk in zip(w, parts)))
    got = np.asarray(pdf_log(g, jnp.asarray(x, dtype)), np.float64)
    # float32: (x - mu) / sigma to ~1e-7 of |x| / sigma, squared (~2e-3 at |x| = 1000).
    tol = {jnp.float64: 1e-10, jnp.float32: 1e-4 * (1 + offset / 50)}[dtype]
    np.testing.assert_allclose(got, expected, rtol=tol, atol=tol)


def test_truncated_far_tail():
    """A component 40 sigma outside the box samples its exponential-like tail correctly."""
    g = GaussianMixture(jax.random.key(0), jnp.zeros(1), jnp.ones(1), 1)
    g = eqx.tree_at(
        lambda m: (m.means, m.log_scales), g, (jnp.array([[5.0]]), jnp.log(jnp.array([[0.1]])))
    )
    x, p = sample(g, jax.random.key(1), 20_000)
    # Density ~ 400 exp(-400 (1 - x)) near x = 1: mean 1 - 1/400.
    assert abs(float(jnp.mean(x)) - (1 - 1 / 400)) < 1e-4
    assert bool(jnp.all(jnp.isfinite(p)))


@pytest.mark.parametrize("name", ["gm", "grid", "mix", "linear", "partition"])
def test_gradients_finite(key, name):
    prop = _proposals(key)[name]
    x, _ = sample(prop, key, 256)
    # filter_grad: a Partition's tree structure is integer arrays.
    grads = eqx.filter_jit(eqx.filter_grad(lambda q: jnp.sum(q.log_pdf(x))))(prop)
    leaves = [g for g in jax.tree.leaves(grads) if g is not None]
    assert leaves and all(bool(jnp.all(jnp.isfinite(g))) for g in leaves)

    if name == "mix":
        return  # its components are covered; the mixture's own sampler has no parameters

    # Reparameterised gradient of an importance estimate (samples move with the parameters).
    def est(q):
        xs, ps = q.sample(jax.random.key(3), 256)
        return jnp.mean(jnp.sum(xs**2, axis=-1) / ps)

    g2 = eqx.filter_jit(eqx.filter_grad(est))(prop)
    assert all(bool(jnp.all(jnp.isfinite(g))) for g in jax.tree.leaves(g2))


def test_gm_reparameterised_gradient_matches_finite_difference(key):
    """d/dmu E[x] for one truncated normal, against float64 finite differences."""
    g = GaussianMixture(key, 0.0, 1.0, 1)

    @jax.jit
    def mean_x(mu):
        moved = eqx.tree_at(lambda m: m.means, g, jnp.reshape(mu, (1, 1)))
        return jnp.mean(moved.sample(jax.random.key(5), 2000)[0])

    mu = jnp.asarray(0.3)
    grad = jax.grad(mean_x)(mu)
    fd = (mean_x(mu + 1e-5) - mean_x(mu - 1e-5)) / 2e-5
    np.testing.assert_allclose(grad, fd, rtol=1e-4)


def test_jit_vmap(key):
    prop = _proposals(key)["mix"]  # contains the other two
    # jit gives the same points as the eager path (on the grid: eager dispatch is slow).
    with jax.disable_jit():
        x_eager, _ = prop.proposals[1].sample(key, 64)
    np.testing.assert_allclose(sample(prop.proposals[1], key, 64)[0], x_eager, rtol=1e-12)
    xs, ps = jax.jit(jax.vmap(lambda k: prop.sample(k, 16)))(jax.random.split(key, 3))
    assert xs.shape == (3, 16, 2) and ps.shape == (3, 16)
    assert pdf(prop, xs).shape == (3, 16)


def test_grid_refine_vegas_rule(key):
    g = Grid(0.0, 1.0, 8)
    x, p = g.sample(key, 20_000)
    w = (2 * x / p) ** 2
    g2 = g.refine(x, w, alpha=1.0)
    e = np.asarray(g2.edges[0])
    assert e[0] == 0.0 and abs(e[-1] - 1.0) < 1e-12 and np.all(np.diff(e) > 0)
    # f = 2x is larger on the right: the bins shrink there.
    widths = np.diff(e)
    assert widths[-1] < widths[0] / 2
    # alpha = 0 flattens the weights: edges stay uniform.
    np.testing.assert_allclose(g.refine(x, w, alpha=0.0).edges, g.edges, atol=1e-12)
    # Repeated refinement converges towards the optimal density 2x mixed with the rule's
    # 1% defensive share, q = (2x + 0.01)/1.01 (CDF (x^2 + 0.01 x)/1.01). The smoothing of
    # the bin weights keeps the first interior edge about 0.031 below it (the same on every
    # key tried; the others are within 0.02); uniform edges would be 0.23 off.
    @eqx.filter_jit  # (one compiled step for the ten; eagerly each dispatches op by op)
    def step(g, k):
        x, p = g.sample(k, 20_000)
        return g.refine(x, (2 * x / p) ** 2, alpha=0.5)

    for i in range(10):
        g2 = step(g2, jax.random.fold_in(key, i))
    share, levels = 0.01, np.linspace(0, 1, 9) * 1.01
    optimal = (-share + np.sqrt(share**2 + 4 * levels)) / 2
    np.testing.assert_allclose(g2.edges[0], optimal, atol=0.035)


@pytest.mark.parametrize("bins", [64, 256, 1024])
def test_grid_refine_defensive_share_is_fixed_in_bins(bins):
    """Where f = 0 (x > 1/2) the refined grid keeps about two bins at any resolution: the
    defensive share is 1% up to 64 bins and the mass of 0.64 bins above. A share of 1% at
    every resolution would keep 2.9 bins there at 256 and 6.8 at 1024."""
    grid = Grid(0.0, 1.0, bins)
    x = (jnp.arange(bins) + 0.5) / bins
    edges = np.asarray(grid.refine(x, jnp.where(x < 0.5, 1.0, 0.0)).edges[0])
    bins_where_zero = bins - np.interp(0.5, edges, np.arange(bins + 1))
    assert 1.8 < bins_where_zero < 2.2


def test_partition_cells_tile_the_box(key):
    """The leaves are disjoint dyadic boxes covering the box; points are located in theirs."""
    part = _grown_partition(key, LO2, HI2, cells=128)
    lower, upper, mass, leaf = (np.asarray(a) for a in part.cells())
    lower, upper, mass = lower[leaf], upper[leaf], mass[leaf]
    assert 64 < leaf.sum() == int(part.n_cells) <= 128
    np.testing.assert_allclose(np.prod(upper - lower, axis=1).sum(), 3.0, rtol=1e-12)
    np.testing.assert_allclose(mass.sum(), 1.0, rtol=1e-12)
    x, p = sample(part, jax.random.fold_in(key, 1), 5000)
    u = (np.asarray(x) - np.asarray(LO2)) / np.asarray(HI2 - LO2)
    found = np.asarray(part.locate(jnp.asarray(u)))
    lo_all, hi_all, _, _ = (np.asarray(a) for a in part.cells())
    assert np.all(np.asarray(part.child)[found] < 0)
    assert np.all((lo_all[found] <= np.asarray(x)) & (np.asarray(x) <= hi_all[found]))
    # Every point lies in exactly one leaf (the boxes only share faces).
    inside = (np.asarray(x)[:, None] > lower[None]) & (np.asarray(x)[:, None] < upper[None])
    np.testing.assert_array_equal(inside.all(-1).sum(1), 1)
    # The density is P_c / V_c on each leaf.
    vol = np.prod(hi_all[found] - lo_all[found], axis=1)
    np.testing.assert_allclose(p, np.exp(np.asarray(part.log_mass()))[found] / vol, rtol=1e-12)
    # The fitting draw is stratified over the leaves with weights P_c / n_c: exact mass sums.
    xs, log_p, w = part.weighted_draw(key, 1000)
    np.testing.assert_allclose(jnp.sum(w), 1.0, rtol=1e-12)
    np.testing.assert_allclose(log_p, part.log_pdf(xs), rtol=1e-12)


def test_grid_edges_argument():
    e = jnp.array([0.0, 0.1, 0.5, 1.0])
    g = Grid(0.0, 1.0, 3, edges=e)
    np.testing.assert_allclose(g.edges[0], e, atol=1e-12)
    np.testing.assert_allclose(g.pdf(jnp.array([0.05, 0.3, 0.9])), [1 / 0.3, 1 / 1.2, 1 / 1.5])


def test_grid_subdivided_is_the_same_density_in_more_bins(key):
    lo, hi = jnp.array([-1.0, 0.0]), jnp.array([2.0, 0.5])
    logits = 2 * jax.random.normal(key, (2, 5))
    g = eqx.tree_at(lambda q: q.logits, Grid(lo, hi, bins=5), logits)
    fine = g.subdivided(3)
    assert fine.bins == 15 and fine.logits.dtype == g.logits.dtype
    # Every third edge is an edge of the original grid, and each bin is split evenly.
    np.testing.assert_allclose(fine.edges[:, ::3], g.edges, rtol=1e-12, atol=1e-12)
    widths = np.reshape(np.diff(np.asarray(fine.edges)), (2, 5, 3))
    np.testing.assert_allclose(widths, widths[..., :1] * np.ones(3), rtol=1e-9)
    x, _ = g.sample(jax.random.fold_in(key, 1), 1000)
    np.testing.assert_allclose(fine.log_pdf(x), g.log_pdf(x), rtol=1e-12)
    assert g.subdivided(1).bins == 5
    with pytest.raises(ValueError, match="factor"):
        g.subdivided(0)


@pytest.mark.parametrize("bins", [1, 2, 3, 7, 64, 100, 256])
def test_grid_bin_index_is_the_last_edge_at_or_below(bins):
    # The branchless binary search against `searchsorted` on the unit edges, for any number of
    # bins (powers of two and not), on uneven edges, at the edges themselves, between them
    # and outside the box (clipped to the first and last bin). One program computes both: an
    # edge computed in two (an eager `g.edges`, the jitted search) can differ by an ulp with
    # the compiler's arrangement of softmax and cumsum (at XLA's level 0, 16 edge points
    # fell one bin below), and then which bin holds a point on it is a coin toss.
    d = 3
    lo, hi = jnp.array([-1.0, 0.0, 2.0]), jnp.array([2.0, 1.0, 2.5])
    logits = 2 * jax.random.normal(jax.random.key(bins), (d, bins))
    g = eqx.tree_at(lambda q: q.logits, Grid(lo, hi, bins=bins), logits)
    u = jax.random.uniform(jax.random.key(0), (500, d), minval=-0.2, maxval=1.2)

    @eqx.filter_jit
    def searched(g, u):
        e = g.edges.T
        x = jnp.concatenate([lo + (hi - lo) * u, e, (e[:-1] + e[1:]) / 2])
        unit = g._unit_edges()
        t = (x - lo) / (hi - lo)
        search = jax.vmap(lambda ej, tj: jnp.searchsorted(ej, tj, side="right") - 1, (0, 1), 1)
        return g.bin_index(x), search(unit, t)

    index, expected = searched(g, u)
    np.testing.assert_array_equal(index, np.clip(expected, 0, bins - 1))


def test_gm_from_weighted_samples(key):
    """Weighted EM on uniform samples weighted by f finds f's two separated peaks."""
    centres = jnp.array([[0.25, 0.7], [0.75, 0.3]])
    s = 0.05
    f = lambda x: 0.3 * jnp.exp(-jnp.sum((x - centres[0]) ** 2) / (2 * s * s)) + 0.7 * jnp.exp(
        -jnp.sum((x - centres[1]) ** 2) / (2 * s * s)
    )
    x = jax.random.uniform(key, (20_000, 2))
    gm = from_samples(x, jax.vmap(f)(x), jnp.zeros(2), jnp.ones(2), components=2)
    order = jnp.argsort(gm.means[:, 0])
    np.testing.assert_allclose(gm.means[order], centres, atol=0.01)
    np.testing.assert_allclose(jnp.exp(gm.log_scales[order]), s, rtol=0.1)
    np.testing.assert_allclose(jax.nn.softmax(gm.logits)[order], [0.3, 0.7], atol=0.03)
    # Zero weights (e.g. f underflowed) are never picked as starting means.
    w0 = jnp.zeros(100).at[50].set(1.0).at[7].set(0.5)
    pts = jax.random.uniform(key, (100, 2))
    two = from_samples(pts, w0, jnp.zeros(2), jnp.ones(2), 2, iterations=0)
    np.testing.assert_allclose(jnp.sort(two.means[:, 0]), jnp.sort(pts[jnp.array([50, 7]), 0]))
    # Seeding does not depend on the box's scale: a light but separate cluster far away
    # (distance > 1) still gets a component.
    kc, kf = jax.random.split(key)
    near = 3.0 * jax.random.normal(kc, (50,))
    pts1 = jnp.concatenate([near, jnp.full((5,), 15.0)])
    w1 = jnp.concatenate([jnp.ones(50), jnp.full((5,), 0.5)])
    for scale in (1.0, 0.01):
        seeded = from_samples(scale * pts1, w1, -20.0 * scale, 20.0 * scale, 2, iterations=0)
        assert float(jnp.max(seeded.means)) == pytest.approx(15.0 * scale), seeded.means
    # float32 far from the origin: the EM variance is computed from deviations.
    far = 1000.5 + 0.02 * jax.random.normal(kf, (2000, 2))
    lo32, hi32 = jnp.full(2, 1000.0, jnp.float32), jnp.full(2, 1001.0, jnp.float32)
    g32 = from_samples(far.astype(jnp.float32), jnp.ones(2000, jnp.float32), lo32, hi32, 1,
                       prior=0.0, min_scale=1e-4)
    np.testing.assert_allclose(jnp.exp(g32.log_scales), 0.02, rtol=0.1)
    # A spike of weight on one sample does not collapse a component below the floor.
    w = jnp.zeros(100).at[3].set(1.0)
    spiky = from_samples(pts, w, jnp.zeros(2), jnp.ones(2), 2, min_scale=0.02)
    assert float(jnp.min(jnp.exp(spiky.log_scales))) >= 0.02 - 1e-12
    with pytest.raises(ValueError, match="weights"):
        GaussianMixture.from_samples(pts, jnp.ones(99), jnp.zeros(2), jnp.ones(2), 2)
    with pytest.raises(ValueError, match="components"):
        GaussianMixture.from_samples(pts[:1], jnp.ones(1), jnp.zeros(2), jnp.ones(2), 2)
    with pytest.raises(ValueError, match="min_scale"):
        GaussianMixture.from_samples(pts, w, jnp.zeros(2), jnp.ones(2), 2, min_scale=0.0)


def test_gm_em_until_noise_stops_once_steps_gain_less_than_the_noise(key):
    # The same EM steps, stopped once one gains less weighted log-likelihood than that
    # mean's sampling error: a fit as good as 50 steps' within that error, after fewer.
    centres = jnp.array([[0.25, 0.7], [0.75, 0.3]])
    f = lambda x: 0.3 * jnp.exp(-jnp.sum((x - centres[0]) ** 2) / 0.005) + 0.7 * jnp.exp(  # noqa: E731
        -jnp.sum((x - centres[1]) ** 2) / 0.02)
    x = jax.random.uniform(key, (4096, 2))
    w = jax.vmap(f)(x)
    w = w / jnp.sum(w)
    lo, hi = jnp.zeros(2), jnp.ones(2)
    early = from_samples(x, w, lo, hi, 4, until_noise=True)
    steps = next((k for k in range(2, 50) if np.array_equal(
        from_samples(x, w, lo, hi, 4, iterations=k).means, early.means)), None)
    assert steps is not None  # (the fit of some number of steps below 50)
    full = from_samples(x, w, lo, hi, 4)
    log_p = pdf_log(full, x)
    mean = jnp.sum(w * log_p)
    noise = jnp.sqrt(jnp.sum(w * (log_p - mean) ** 2) * jnp.sum(w**2))
    assert float(mean - jnp.sum(w * pdf_log(early, x))) <= 3 * float(noise)
    # Reverse-mode derivatives pass: the fit is a constant of its samples.
    grad = jax.grad(lambda s: jnp.sum(GaussianMixture.from_samples(
        s * x, w, lo, hi, 4, until_noise=True).means))(1.0)
    assert float(grad) == 0.0


def test_mixture_weights_fixed_unless_trained(key):
    props = _proposals(key)
    mix = props["mix"]
    g = jax.grad(lambda m: jnp.sum(m.log_pdf(jnp.array([[0.5, 0.5]]))))(mix)
    assert float(jnp.max(jnp.abs(g.log_weights))) == 0.0
    mix_t = Mixture(mix.proposals, (0.5, 0.3, 0.2), train_weights=True)
    g = jax.grad(lambda m: jnp.sum(m.log_pdf(jnp.array([[0.5, 0.5]]))))(mix_t)
    assert float(jnp.max(jnp.abs(g.log_weights))) > 0.0


def test_bad_inputs(key):
    with pytest.raises(ValueError, match="components"):
        GaussianMixture(key, 0.0, 1.0, components=0)
    with pytest.raises(ValueError, match="lo"):
        GaussianMixture(key, 1.0, 0.0)
    with pytest.raises(TypeError, match="key"):
        GaussianMixture(0, 0.0, 1.0)
    with pytest.raises(ValueError, match="bins"):
        Grid(0.0, 1.0, bins=0)
    with pytest.raises(TypeError, match="bins"):
        Grid(0.0, 1.0, bins=2.5)
    with pytest.raises(ValueError, match="edges"):
        Grid(0.0, 1.0, 3, edges=jnp.array([0.0, 0.6, 0.5, 1.0]))
    with pytest.raises(ValueError, match="bins"):
        PiecewiseLinear(0.0, 1.0, bins=0)
    with pytest.raises(ValueError, match="lo"):
        PiecewiseLinear(jnp.ones(2), jnp.zeros(2))
    with pytest.raises(ValueError, match="max_cells"):
        Partition(0.0, 1.0, max_cells=0)
    with pytest.raises(ValueError, match="lo"):
        Partition(jnp.ones(2), jnp.zeros(2))
    with pytest.raises(ValueError, match="x"):
        PiecewiseLinear(jnp.zeros(2), jnp.ones(2)).pdf(jnp.zeros(3))
    with pytest.raises(ValueError, match="weights"):
        Mixture((Uniform(0.0, 1.0), Uniform(0.0, 1.0)), (1.0, -0.5))
    with pytest.raises(ValueError, match="weights"):
        Mixture((Uniform(0.0, 1.0),), (0.5, 0.5))
    with pytest.raises(ValueError, match="shape"):
        Mixture((Uniform(0.0, 1.0), Uniform(jnp.zeros(2), jnp.ones(2))))
    with pytest.raises(TypeError, match="proposals"):
        Mixture((Uniform(0.0, 1.0), "not a proposal"))
    with pytest.raises(ValueError, match="x"):
        Grid(jnp.zeros(2), jnp.ones(2)).pdf(jnp.zeros(3))
    with pytest.raises(ValueError, match="n"):
        Grid(0.0, 1.0).sample(key, 0)
    with pytest.raises(ValueError, match="alpha"):
        Grid(0.0, 1.0).refine(jnp.zeros(4), jnp.ones(4), alpha=-1.0)
    with pytest.raises(ValueError, match="weights"):
        Grid(0.0, 1.0).refine(jnp.zeros(4), jnp.ones(3))


def test_grid_bins_tile_the_unit_interval_exactly_in_float32():
    # A grid trained on a resonance has bins far narrower than the others; in float32 an
    # edge's last place is then a sizeable share of such a bin. Widths that differ from
    # their edges' differences make bins overlap or leave gaps: a bias (5e-4 of a 4-D
    # Breit-Wigner's integral, 100 standard errors). Compiled as the streams compile it.
    logits = jnp.concatenate([jnp.zeros((2, 200)), jnp.full((2, 56), -9.0)], axis=1)
    logits = jnp.roll(logits, 100, axis=1).astype(jnp.float32)
    g = eqx.tree_at(lambda q: q.logits, Grid(jnp.zeros(2, jnp.float32),
                                             jnp.ones(2, jnp.float32), bins=256), logits)
    left, width, log_w = (np.asarray(t).reshape(2, 256) for t in jax.jit(Grid.lookup_table)(g))
    right = np.concatenate([left[:, 1:], np.ones((2, 1), np.float32)], axis=1)
    assert left.dtype == np.float32 and np.all(left[:, 0] == 0)
    assert np.array_equal(width, right - left)  # exactly
    np.testing.assert_allclose(log_w, np.log(256 * width.astype(np.float64)), atol=1e-6)
