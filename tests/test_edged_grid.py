"""A trained grid's bins bent to a singularity on a face (`EdgedGrid`, `GridQMC`'s map)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmc
from jaxmc._auto._nets import mapped_net_values
from jaxmc._methods._edged_grid import EDGE_OVERSHOOT, EdgedGrid, edge_powers, edged
from jaxmc.proposals import Grid

from .helpers import assert_unbiased_and_honest, auto_against, box


def face_singular(x):
    """x_0^(-1/2) (1 - x_1)^(-1/2) / 4: singular on the lower face of axis 0 and the upper
    face of axis 1; its integral over the unit square is 1."""
    return 0.25 / jnp.sqrt(x[0] * (1 - x[1]))


def _power_law_grid(dtype=jnp.float64):
    # Exact power laws: e_k = (k/N)^2 from axis 0's lower face, 1 - (1 - k/N)^1.5 on axis 1.
    t = np.linspace(0.0, 1.0, 257)
    edges = np.stack([t**2, 1 - (1 - t) ** 1.5])
    lo, hi = (b.astype(dtype) for b in box(2))
    return Grid(lo, hi, bins=256, edges=edges)


def test_edge_powers_read_the_law_of_the_edges():
    low, high = edge_powers(_power_law_grid())
    np.testing.assert_allclose(low, [2 * EDGE_OVERSHOOT, 1.0], rtol=1e-9)
    np.testing.assert_allclose(high, [1.0, 1.5 * EDGE_OVERSHOOT], rtol=1e-9)
    assert bool(edged(_power_law_grid()).powered)
    # In float32 the floats near hi = 1 are 6e-8 apart: that face is not bent (lo = 0 is).
    low, high = edge_powers(_power_law_grid(jnp.float32))
    np.testing.assert_allclose(low, [2 * EDGE_OVERSHOOT, 1.0], rtol=1e-5)
    np.testing.assert_array_equal(high, [1.0, 1.0])
    # An even grid, or one with no law at its faces, is left as it is.
    even = Grid(*box(2), bins=256)
    assert not bool(edged(even).powered)


@pytest.mark.parametrize("dtype, rtol", [(jnp.float64, 1e-8), (jnp.float32, 2e-3)])
def test_the_edged_map_has_the_density_it_reports(dtype, rtol):
    # q(x) is the inverse of the map's Jacobian (diagonal: one axis at a time), at points
    # over the whole square and in the bins at both faces, where the powers bend it.
    grid = _power_law_grid(dtype)
    low, high = edge_powers(grid)
    bent = EdgedGrid(grid, low, high)
    u = jax.random.uniform(jax.random.key(1), (512, 2), dtype)
    u = jnp.concatenate([u, u * 16 / 256, 1 - u * 16 / 256])  # (the first and last 16 bins)
    x, log_q = bent.map(u)
    jacobians = jax.vmap(jax.jacfwd(lambda v: bent.map(v[None])[0][0]))(u)
    np.testing.assert_allclose(np.abs(np.linalg.det(jacobians)) * np.exp(log_q), 1.0, rtol=rtol)
    assert np.all((np.asarray(x) > 0) & (np.asarray(x) < 1))
    # The bins keep their mass 1/N: the edges they map to are the grid's (beyond the even
    # first 16 from a bent face, whose 16th edge stays).
    edges = np.asarray(grid.edges)
    for k in (16, 17, 128, 200, 239, 240):
        at = jnp.full((1, 2), k / 256, dtype)
        np.testing.assert_allclose(np.asarray(bent.map(at)[0])[0], edges[:, k], rtol=10 * rtol)


def _trained(f, d, key=0):
    from jaxmc._stream._rounds import train_vegas_plus, uniform_grid

    lo, hi = box(d)
    return train_vegas_plus(jax.random.key(key), f, uniform_grid(lo, hi, bins=256), 10, 2048,
                            False).grid


def test_a_trained_grid_is_bent_at_its_singular_faces_only():
    # The slopes of the grid trained on x_0^-1/3 x_1^-1/2 (1 - x_2)^-1/2 with a smooth
    # fourth axis, as `auto` trains it at 1e5: below the true 1.5, 2, 2 at the singular faces
    # (read 1.33, 1.67, 1.75: hence `EDGE_OVERSHOOT`), 1 elsewhere; on a round peak, none.
    def f(x):
        return x[0] ** (-1 / 3) / jnp.sqrt(x[1] * (1 - x[2])) * (1 + x[3])

    grid = edged(_trained(f, 4))
    assert bool(grid.powered)
    slopes = np.asarray(grid.low) / EDGE_OVERSHOOT
    assert 1.25 < slopes[0] < 1.7 and 1.6 < slopes[1] < 2.2, slopes
    assert slopes[2] == slopes[3] == 1 / EDGE_OVERSHOOT, slopes
    high = np.asarray(grid.high)
    assert 1.6 < high[2] / EDGE_OVERSHOOT < 2.2 and np.all(high[[0, 1, 3]] == 1), high
    peak = _trained(lambda x: jnp.exp(-jnp.sum((x - 0.5) ** 2) / 0.02), 4)
    assert not bool(edged(peak).powered)


def test_values_through_the_bent_grid_are_bounded():
    # Through the grid alone x^-1/2's values f/q have a power-law tail (the first bins'
    # f/q grows without bound); through the bent one they stay within 2.5x their mean on
    # 2^18 points, and the nets' error falls 1000x in variance.
    from jaxmc._diagnostics import pareto_k, tail_of

    trained = _trained(face_singular, 2)
    spread = {}
    for name, grid in (("grid", trained), ("bent", edged(trained))):
        y, _ = mapped_net_values(jax.random.key(3), grid, face_singular, False, 15)
        flat = jnp.reshape(y, (-1,))
        spread[name] = float(jnp.var(jnp.mean(y, axis=1)))
        k_hat = float(pareto_k(tail_of(flat)))
        if name == "bent":
            assert float(jnp.max(flat)) < 2.5 * float(jnp.mean(flat)) and k_hat < 0, k_hat
        else:
            assert float(jnp.max(flat)) > 10 * float(jnp.mean(flat)) and k_hat > 0.2, k_hat
    assert spread["bent"] < spread["grid"] / 1000, spread


def test_auto_takes_the_bent_grid_on_a_face_singularity():
    # QMC through the bent grid, 10x and more below the refining grid's error
    # (`method="adaptive"`) on the same budget, each within 5 of its standard errors.
    rms, _ = auto_against(face_singular, 1.0, *box(2), 2**17, "grid_qmc", "adaptive")
    assert rms["auto"] < rms["adaptive"] / 10, rms


def test_the_bent_stream_is_unbiased_and_honest():
    # QMC through the bent grid (a plan: the grid trained once), over 64 keys: the replicas'
    # spread is an unbiased estimate of the variance (no tail the replicas miss together).
    lo, hi = box(2)
    plan = jaxmc.methods.GridQMC(_trained(face_singular, 2))
    assert bool(edged(plan.grid).powered)
    keys = jax.random.split(jax.random.key(100), 64)
    runs = jax.jit(jax.vmap(lambda k: jaxmc.integrate(k, face_singular, lo, hi, n=2**15,
                                                      method=plan)))(keys)
    assert_unbiased_and_honest(runs, 1.0)


def test_the_bent_grid_in_one_dimension_and_in_float32():
    # Scalar bounds: a 1-D grid, bent as well. In float32 (singular on the lower faces, which
    # it resolves: `edge_powers`) the estimate is within 5 of its standard errors.
    n = 2**16
    line = jaxmc.integrate(jax.random.key(7), lambda x: 0.5 / jnp.sqrt(x), 0.0, 1.0, n=n)
    assert line.method == "grid_qmc" and line.mean.shape == (), line.pilot
    assert abs(float(line.mean) - 1) < 5 * float(line.stderr)
    lo32, hi32 = (b.astype(jnp.float32) for b in box(2))
    lower_faces = lambda x: 0.25 / jnp.sqrt(x[0] * x[1])  # noqa: E731
    single = jaxmc.integrate(jax.random.key(7), lower_faces, lo32, hi32, n=n)
    assert single.method == "grid_qmc" and single.mean.dtype == jnp.float32, single.pilot
    assert abs(float(single.mean) - 1) < 5 * float(single.stderr) + 1e-6
