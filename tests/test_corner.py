"""`integrate(method="auto")`'s cube bent towards a singular corner (`"corner_qmc"`, `_corner`)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmc._diagnostics import pareto_k, tail_of
from jaxmc._estimators._corner import (
    CornerMap,
    bends_corner,
    corner_probe,
    corner_probe_evaluations,
)
from jaxmc._estimators._edged_grid import EDGE_OVERSHOOT
from jaxmc._estimators._pilot_record import Pilot, dropped

from .helpers import assert_eager_method_honest, auto_against, box


D, A = 4, 1.5


def corner_sum(x):
    """(x_1 + ... + x_4)^-3/2: singular at the corner 0, with bounded marginals."""
    return jnp.sum(x, axis=-1) ** -A


# Inclusion-exclusion over the box's corners: G(s) = s^(d - a) / prod_k (k - a).
EXACT = sum((-1) ** k * math.comb(D, k) * (D - k) ** (D - A) for k in range(D + 1)) \
    / np.prod([k - A for k in range(1, D + 1)])


def _probe(f, d, dtype=jnp.float64):
    lo, hi = (b.astype(dtype) for b in box(d))
    x = jax.random.uniform(jax.random.key(0), (1024, d), dtype)
    return corner_probe(f, True, lo, hi, x, f(x))


@pytest.mark.parametrize("f, d, toward_hi, power", [
    (corner_sum, D, [False] * D, [EDGE_OVERSHOOT * D / (D - A)] * D),
    (lambda x: jnp.sum(1 - x, axis=-1) ** -A, D, [True] * D, [EDGE_OVERSHOOT * D / (D - A)] * D),
    # An edge of the box: only the axes that meet there are bent, at 2 / (2 - 0.8).
    (lambda x: (x[..., 0] + x[..., 1]) ** -0.8, 4, [False] * 4, [2.0, 2.0, 1.0, 1.0]),
    # A product: 6 / (6 - 2), as each factor's own 1 / (1 - 1/3).
    (lambda x: jnp.prod(x ** (-1 / 3), axis=-1), 6, [False] * 6, [EDGE_OVERSHOOT * 1.5] * 6),
])
def test_the_probe_reads_the_corner_and_its_power(f, d, toward_hi, power):
    corner, singular = _probe(f, d)
    assert bool(singular)
    np.testing.assert_allclose(corner.power, power, rtol=2e-3)
    meets = np.asarray(power) > 1  # (the other axes' faces are the vote's, and do not matter)
    np.testing.assert_array_equal(np.asarray(corner.toward_hi)[meets], np.asarray(toward_hi)[meets])


@pytest.mark.parametrize("f", [
    lambda x: (1 + jnp.sum(x, axis=-1) / 4) ** -5,  # Genz's corner peak: levels off
    lambda x: jnp.exp(-jnp.sum((x - 0.5) ** 2, axis=-1) / 0.01),  # a peak inside
    lambda x: jnp.exp(-jnp.sum(x**2, axis=-1) / 0.01),  # a peak at the corner
    lambda x: jnp.prod(jnp.abs(x - 1 / 3) ** -0.5, axis=-1),  # singular inside the box
])
def test_the_probe_finds_no_corner_where_f_is_bounded_there(f):
    corner, singular = _probe(f, D)
    assert not bool(singular)
    np.testing.assert_array_equal(corner.power, 1.0)


def test_in_float32_a_corner_on_the_upper_faces_is_not_bent():
    # The floats near hi = 1 are 6e-8 apart: a face there is not bent (`edge_powers`); one at
    # lo = 0 is.
    upper = lambda x: jnp.sum(1 - x, axis=-1) ** -A  # noqa: E731
    assert not bool(_probe(upper, D, jnp.float32)[1])
    corner, singular = _probe(corner_sum, D, jnp.float32)
    assert bool(singular)
    np.testing.assert_allclose(corner.power, EDGE_OVERSHOOT * D / (D - A), rtol=2e-3)


def test_the_corner_maps_density_is_its_jacobians_inverse():
    lo, hi = jnp.asarray([-1.0, 0.0, 2.0]), jnp.asarray([1.0, 0.5, 5.0])
    corner = CornerMap(lo, hi, jnp.asarray([False, True, False]), jnp.asarray([2.4, 1.7, 1.0]))
    u = jax.random.uniform(jax.random.key(1), (64, 3), jnp.float64)
    x, log_q = corner.map(u)
    jacobian = jax.vmap(jax.jacfwd(lambda v: corner.map(v[None])[0][0]))(u)
    np.testing.assert_allclose(log_q, -jnp.log(jnp.abs(jnp.linalg.det(jacobian))), rtol=1e-10)
    assert bool(jnp.all((x >= lo) & (x <= hi)))
    # On the upper face of axis 1, the smallest z lands nearest hi.
    assert float(corner.map(jnp.asarray([[0.5, 1e-6, 0.5]]))[0][0, 1]) > 0.5 - 1e-9


def test_through_the_corner_map_f_over_q_is_bounded():
    # Uniform points: f's largest value 184x its mean on 2^21 points, a power-law tail
    # (k-hat 3/8); through the map, bounded (at most 4.4x on 2^21 points with p = 2).
    corner, _ = _probe(corner_sum, D)
    u = jax.random.uniform(jax.random.key(2), (1 << 18, D), jnp.float64)
    x, log_q = corner.map(u)
    values = corner_sum(x) / jnp.exp(log_q)
    assert abs(float(jnp.mean(values)) / EXACT - 1) < 5 * float(jnp.std(values)) / EXACT / 2**9
    assert float(jnp.max(values) / jnp.mean(values)) < 10
    assert float(pareto_k(tail_of(values))) < 0
    assert float(pareto_k(tail_of(corner_sum(u)))) > 0.2


def test_auto_takes_the_corner_map_on_a_corner_singularity():
    # The grid's density is bounded at the corner, f/q not; QMC through the bent cube errs
    # 5x and more below the refining grid (`method="adaptive"`), each within 5 standard errors.
    rms, runs = auto_against(corner_sum, EXACT, *box(D), 100_000, "corner_qmc", "adaptive")
    assert rms["auto"] < rms["adaptive"] / 5, rms
    for est in runs:  # (the probe's evaluations and its nets', taken from the stream's)
        assert est.pilot.candidates[-1] == "corner_qmc"
        assert est.pilot.evaluations[-1] == corner_probe_evaluations(D) + 4096
        assert int(est.n) <= 100_000


def test_the_corner_stream_is_unbiased_and_honest():
    # Over the keys that took it (at least 40 of 48).
    assert_eager_method_honest(corner_sum, EXACT, *box(D), 2**15, "corner_qmc", range(200, 248),
                               least=40)


def test_a_grid_unbent_at_the_corner_is_no_candidate():
    corner = CornerMap(*box(3), jnp.asarray([False, True, False]), jnp.asarray([2.0, 2.0, 1.0]))
    bent = jnp.asarray([1.5, 1.0, 1.0]), jnp.asarray([1.0, 1.5, 1.0])
    assert bool(bends_corner(corner, *bent))  # (axis 2 does not meet at the corner)
    assert not bool(bends_corner(corner, bent[1], bent[0]))  # the other faces
    assert not bool(bends_corner(corner, jnp.ones(3), jnp.ones(3)))
    # Dropped, the grid's figures are inf and the cheapest of the rest is chosen.
    pilot = Pilot(("qmc", "adaptive", "grid_qmc"), jnp.asarray([0.5, 0.01, 0.001]),
                  jnp.asarray([0.5, 0.03, 0.002]), jnp.asarray(2, jnp.int32), (1, 2, 3))
    without = dropped(pilot, "grid_qmc")
    assert int(without.choice) == 1 and np.isinf(without.cost[2]), without
    assert int(dropped(pilot, "qmc").choice) == 2
