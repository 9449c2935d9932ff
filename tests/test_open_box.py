"""Open-box sampling: no point set, warp, proposal or `integrate` path returns u = 0 or 1,
or a point on a face of the box, so integrable endpoint singularities never crash a run.

Float32 cases are the adversarial ones (24-bit rounding lands on faces): they run under
the suite's x64 setting by passing float32 dtypes and bounds explicitly.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.scipy.special import ndtri

import jaxmc
from jaxmc import _random, points, warps
from jaxmc._box import to_box
from jaxmc._estimators._integrate import METHODS
from jaxmc._fit._vegas import stratified_unit_points
from jaxmc._points._common import uint32_to_unit
from jaxmc._points._registry import POINT_SETS, unit_points
from jaxmc.proposals import (
    Flow,
    GaussianMixture,
    Grid,
    Mixture,
    Partition,
    PiecewiseLinear,
    Uniform,
)


DTYPES = [jnp.float32, jnp.float64]


def assert_open_unit(u, label):
    u = np.asarray(u)
    assert np.all(np.isfinite(u)), label
    assert u.min() > 0.0 and u.max() < 1.0, f"{label}: min {u.min()!r}, max {u.max()!r}"


def assert_inside(x, lo, hi, label):
    x, lo, hi = np.asarray(x), np.asarray(lo), np.asarray(hi)
    assert np.all(np.isfinite(x)), label
    below, above = ~(x > lo), ~(x < hi)
    assert not below.any() and not above.any(), (
        f"{label}: {below.sum()} points at or below lo, {above.sum()} at or above hi"
    )


# -------------------------------------------------------------------- uniform variates


@pytest.mark.parametrize("dtype", [jnp.float16, jnp.bfloat16, *DTYPES])
def test_uniform_variates_are_open(key, dtype):
    # 2^22 draws hit the first and last of float32's 2^23 cells with probability ~0.4.
    u = _random.uniform(key, (2**22,), dtype)
    assert u.dtype == dtype
    assert_open_unit(u.astype(jnp.float64), jnp.dtype(dtype).name)


@pytest.mark.parametrize("dtype, bits", [(jnp.float32, 24), (jnp.float64, 53)])
def test_uniform_variates_are_cell_midpoints(key, dtype, bits):
    # (j + 1/2) 2^-k: odd multiples of 2^-(k+1), so 1 - u has the same law and E u = 1/2.
    u = np.asarray(_random.uniform(key, (4096,), dtype), np.float64)
    scaled = u * 2.0**bits
    np.testing.assert_array_equal(scaled, np.round(scaled))
    assert np.all(np.round(scaled) % 2 == 1)
    u_min, u_max = 2.0**-bits, 1 - 2.0**-bits
    assert np.asarray(1 - jnp.asarray(u_max, dtype)) == u_min


@pytest.mark.parametrize("dtype", DTYPES)
def test_uint32_words_map_into_the_open_interval(dtype):
    words = jnp.array([0, 1, 255, 256, 2**31, 2**32 - 256, 2**32 - 1], jnp.uint32)
    u = uint32_to_unit(words, jnp.dtype(dtype))
    assert_open_unit(u, "uint32_to_unit")
    # Only the word(s) that would give 0 move; the others are x / 2^32 (truncated in float32).
    expected = np.asarray(words, np.float64) / 2**32
    if dtype == jnp.float32:
        expected = np.floor(expected * 2**24) / 2**24
    moved = expected == 0
    np.testing.assert_array_equal(np.asarray(u)[~moved], expected[~moved])


# -------------------------------------------------------------------- point sets


def _point_sets(key, dtype):
    """Every public point set, randomised and not, with adversarial sizes."""
    return {
        "uniform": points.uniform(key, 2**16, 3, dtype=dtype),
        # (k + u) / c rounds to 1 in float32 for the last of many strata.
        "stratified": points.stratified(key, (2**16,), dtype=dtype),
        "stratified 2-D": points.stratified(key, (64, 32), dtype=dtype),
        "latin_hypercube": points.latin_hypercube(key, 2**16, 2, dtype=dtype),
        "latin_hypercube permuted": points.latin_hypercube(key, 2**16 + 1, 1, dtype=dtype),
        "halton": points.halton(4096, 4, dtype=dtype),  # index 0 is the origin
        "halton scrambled": points.halton(4096, 4, key=key, dtype=dtype),
        "sobol": points.sobol(4096, 4, dtype=dtype),  # point 0 is the origin
        "sobol scrambled": points.sobol(2**16, 4, key=key, dtype=dtype),
        "sobol far": points.sobol(1024, 2, skip=2**31 - 1024, dtype=dtype),
        "lattice": points.lattice(4096, 4, dtype=dtype),  # point 0 is the origin
        "lattice shifted": points.lattice(2**16, 4, key=key, dtype=dtype),
        "lattice odd": points.lattice(1000, 3, dtype=dtype),
        "shuffle": points.shuffle(key, points.sobol(256, 2, dtype=dtype)),
    }


@pytest.mark.parametrize("dtype", DTYPES)
def test_point_sets_lie_in_the_open_cube(key, dtype):
    for name, x in _point_sets(key, dtype).items():
        assert x.dtype == dtype, name
        assert_open_unit(x, f"{name} {jnp.dtype(dtype).name}")


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("name", sorted(POINT_SETS))
def test_registered_point_sets_lie_in_the_open_cube(key, name, dtype):
    # Every named set the estimators use (incl. `jax.random.uniform`'s stream).
    counts = (64, 64) if name == "stratified" else None
    x = unit_points(name, key, 4096, 2, dtype=dtype, counts=counts)
    assert_open_unit(x, f"{name} {jnp.dtype(dtype).name}")


def test_lcg_lies_in_the_open_interval():
    # The full-period generator x -> x + 1 mod 16 from 15 visits the state 0 first.
    assert_open_unit(points.lcg(15, 16, a=1, c=1, m=16), "lcg")


def test_vegas_plus_strata_points_lie_in_the_open_cube():
    # The last hypercube's (c + r) / s rounds to 1 for r just below 1.
    for dtype in DTYPES:
        strata = (1000,)
        raw = jnp.full((1000, 1), 1 - 2.0 ** -(jnp.finfo(dtype).nmant + 1), dtype)
        draw = stratified_unit_points(raw, jnp.ones((1000,), jnp.int32), strata)
        assert_open_unit(draw.u, jnp.dtype(dtype).name)


# -------------------------------------------------------------------- boxes and proposals


# Far from the origin and 8 ulps wide in float32 (7 floats inside), and one face at 0.
FAR = (jnp.array([1e4, 0.0], jnp.float32), jnp.array([1e4 + 2**-7, 1e-3], jnp.float32))
BOXES = {
    "unit float64": (jnp.array([0.0, -1.0]), jnp.array([1.0, 2.0])),
    "far and narrow float32": FAR,
    "scalar far float32": (FAR[0][0], FAR[1][0]),
}


def test_to_box_never_returns_a_face():
    for label, (lo, hi) in BOXES.items():
        dtype = lo.dtype
        one = 1 - 2.0 ** -(jnp.finfo(dtype).nmant + 1)
        u = jnp.array([0.0, 2.0 ** -(jnp.finfo(dtype).nmant + 1), 0.5, one, 1.0], dtype)
        u = u[:, None] if lo.ndim else u
        assert_inside(to_box(u, lo, hi), lo, hi, label)
        # The affine map's derivative passes through unchanged, also where it was clipped.
        grad = jax.grad(lambda a: jnp.sum(to_box(u, a, hi)))(lo)
        np.testing.assert_allclose(grad, jnp.broadcast_to(jnp.sum(1 - u), lo.shape), rtol=1e-6)


def _unit_maps(key, lo, hi):
    """The proposals that are maps of the unit cube (they have `map(u)`)."""
    # A grid with very uneven bins (widths 1/2, 1/4, ..., 2^-8 of the box), as adaptation
    # leaves them; set through the logits, since such edges are not floats of a narrow box.
    d = 1 if lo.ndim == 0 else lo.shape[0]
    widths = 2.0 ** -jnp.arange(1, 9, dtype=lo.dtype)
    uneven = eqx.tree_at(lambda g: g.logits, Grid(lo, hi, 8), jnp.tile(jnp.log(widths), (d, 1)))
    return {
        "Grid": Grid(lo, hi, 8),
        "Grid uneven": uneven,
        "PiecewiseLinear": PiecewiseLinear(lo, hi, 4),
        "Flow": Flow(key, lo, hi, bins=4, hidden=8, init_scale=0.5),
    }


def _proposals(key, lo, hi):
    k1, k2 = jax.random.split(key)
    return {
        "Uniform": Uniform(lo, hi),
        **_unit_maps(k1, lo, hi),
        "Partition": Partition(lo, hi, 4),
        "GaussianMixture": GaussianMixture(k2, lo, hi, 3),
        "Mixture": Mixture((Uniform(lo, hi), Grid(lo, hi, 4)), (0.5, 0.5)),
    }


@eqx.filter_jit
def _draws(proposal, key, n):
    ks, kw = jax.random.split(key)
    x, p = proposal.sample(ks, n)
    return x, p, proposal.pdf(x), proposal.weighted_draw(kw, n)


@pytest.mark.parametrize("box", ["unit float64", "far and narrow float32"])
def test_proposals_sample_inside_the_open_box(key, box):
    lo, hi = BOXES[box]
    for name, proposal in _proposals(key, lo, hi).items():
        label = f"{name} on {box}"
        x, p, p_at_x, (xw, log_p, _) = _draws(proposal, key, 4096)
        assert_inside(x, lo, hi, label)
        p_at_x = np.asarray(p_at_x)
        assert np.all(np.isfinite(p)) and np.all(np.asarray(p) > 0), label
        assert np.all(np.isfinite(p_at_x)) and np.all(p_at_x > 0), label
        if box == "unit float64":  # the density returned is the density at the point
            np.testing.assert_allclose(p, p_at_x, rtol=1e-9, err_msg=label)
        assert_inside(xw, lo, hi, f"{label} (weighted_draw)")
        assert np.all(np.isfinite(np.asarray(log_p))), label


@pytest.mark.parametrize("box", ["unit float64", "far and narrow float32"])
def test_unit_maps_send_extreme_variates_inside(key, box):
    # The largest and smallest u of the dtype, and u = 0 and 1 themselves.
    lo, hi = BOXES[box]
    dtype, d = lo.dtype, 1 if lo.ndim == 0 else lo.shape[0]
    eps = 2.0 ** -(jnp.finfo(dtype).nmant + 1)
    u = jnp.broadcast_to(jnp.array([0.0, eps, 1 - eps, 1.0], dtype)[:, None], (4, d))
    for name, proposal in _unit_maps(key, lo, hi).items():
        x, log_p = eqx.filter_jit(lambda p, u: p.map(u))(proposal, u)
        assert_inside(x, lo, hi, f"{name} on {box}")
        assert np.all(np.isfinite(np.asarray(log_p))), name


def test_warps_onto_intervals_stay_inside():
    for dtype in DTYPES:
        eps = 2.0 ** -(jnp.finfo(dtype).nmant + 1)
        u = jnp.array([0.0, eps, 0.5, 1 - eps], dtype)
        lo, hi = FAR[0][0].astype(dtype), FAR[1][0].astype(dtype)
        assert_inside(warps.box(u[:, None], lo, hi), lo, hi, "box")
        # x = u^(1/(n+1)) underflows to 0 for n near -1 and rounds to 1 for large n.
        for n in (-0.99, 0.0, 50.0):
            assert_open_unit(warps.power(u, jnp.asarray(n, dtype)), f"power n={n}")
        assert np.all(np.asarray(warps.exponential(u, jnp.asarray(1e30, dtype))) > 0)


# -------------------------------------------------------------------- integrate


@pytest.mark.slow
def test_inverse_square_root_never_raises_on_eight_keys_of_four_million():
    # The acceptance test: 8 keys x 2^22 samples of 1/sqrt(x) on [0, 1] in float32,
    # every method of `integrate`, and `jaxmc.uniform`. A uniform drawn as 0 (or rounded
    # onto a face) gives inf, which `integrate` raises on. The variance is infinite, so
    # finiteness is checked, and the distance from the integral 2 only loosely (a single
    # term is at most 2^12 / 2^22 = 1e-3 once u >= 2^-24).
    keys = jax.random.split(jax.random.key(16), 8)
    lo, hi = jnp.float32(0.0), jnp.float32(1.0)
    f = lambda x: 1 / jnp.sqrt(x)
    runs = {m: (lambda k, m=m: jaxmc.integrate(k, f, lo, hi, n=2**22, method=m)) for m in METHODS}
    runs["jaxmc.uniform"] = lambda k: jaxmc.uniform(k, f, lo, hi, 2**22)
    for name, run in runs.items():
        est = jax.jit(jax.vmap(run))(keys)
        mean, var = np.asarray(est.mean), np.asarray(est.variance)
        assert mean.dtype == np.float32, name
        assert np.all(np.isfinite(mean)) and np.all(np.isfinite(var)), name
        assert np.all(np.asarray(est.n_nonfinite) == 0), name
        assert np.all(np.abs(mean - 2) < 0.05), f"{name}: {mean}"


@pytest.mark.parametrize("method", ["adaptive", "auto"])
def test_inverse_normal_cdf_integrand(method):
    # E[Z^2] = 1 as an integral over u of Phi^{-1}(u)^2: infinite at u = 0 and 1, which the
    # VEGAS+ stream produced in float32 (for seed 2 of these 4, when points were rounded
    # onto the faces). Cut at u = 2^-24 the integral loses ~6e-6, far below the standard
    # error at this n.
    f = lambda x: ndtri(x[0]) ** 2
    lo, hi = jnp.zeros(1, jnp.float32), jnp.ones(1, jnp.float32)
    keys = jax.vmap(jax.random.key)(jnp.arange(4))
    est = jax.jit(jax.vmap(lambda k: jaxmc.integrate(k, f, lo, hi, n=2**16, method=method)))(keys)
    assert np.all(np.asarray(est.n_nonfinite) == 0)
    mean, sdev = np.asarray(est.mean, np.float64), np.sqrt(np.asarray(est.variance, np.float64))
    assert np.all(np.abs(mean - 1.0) < 5 * sdev), f"{method}: {mean} +- {sdev}"
