"""Tests of the direction proposals of `jaxmc.render`: χ² goodness of fit, normalisation,
support, `jaxmc.mis` at shading points against closed forms, jit and vmap, input errors.

Each χ² test bins directions in a frame of the test's own (built without jaxmc), placed
so that the density's jumps (a hemisphere's horizon, a light's rim, a quad's sides)
fall on grid lines of the (cos θ, φ) histogram wherever the geometry allows it.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmc
from jaxmc import warps
from jaxmc.render import (
    BeckmannLobe,
    CosineHemisphere,
    DirectionMixture,
    QuadLight,
    SphereLight,
    UniformHemisphere,
)
from jaxmc.testing import chi2_table

from .helpers import P_FLOOR


N = 100_000  # samples per χ² test


def _frame(axis):
    """Rows (t, b, axis): an orthonormal frame built independently of jaxmc."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t = np.cross(helper, axis)
    t /= np.linalg.norm(t)
    return np.stack([t, np.cross(axis, t), axis])


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


NORMAL = _unit([0.3, -0.5, 0.8])
FRAME = jnp.asarray(_frame(NORMAL))
REF = np.array([0.2, -0.1, 0.3])

# A sphere light whose cone has cos(theta_max) = 0.75 exactly (a grid line of 32 bins on [0, 1]).
LIGHT_AXIS = _unit([0.6, -0.48, 0.64])
LIGHT_DIST = 2.5
LIGHT_RADIUS = LIGHT_DIST * math.sqrt(1.0 - 0.75**2)
LIGHT_FRAME = jnp.asarray(_frame(LIGHT_AXIS))
SPHERE = SphereLight(REF + LIGHT_DIST * LIGHT_AXIS, LIGHT_RADIUS, REF)

# A quad standing on the plane z = ref_z: seen from REF (local frame = world), its
# bottom edge lies on the horizon and its vertical sides on the meridians phi = -15° and
# 30° (grid lines of 48 bins in phi); only the top edge cuts cells.
_PHI1, _PHI2 = math.radians(-15.0), math.radians(30.0)
_A = np.array([math.cos(_PHI1), math.sin(_PHI1), 0.0])
_B = 1.5 * np.array([math.cos(_PHI2), math.sin(_PHI2), 0.0])
QUAD = QuadLight(REF + _A, _B - _A, np.array([0.0, 0.0, 1.2]), REF)

WO = FRAME.T @ jnp.asarray([math.sin(1.0), 0.0, math.cos(1.0)])  # 57° from the normal
LOBE = BeckmannLobe(NORMAL, WO, 0.4)
BRDF = DirectionMixture((BeckmannLobe(NORMAL, WO, 0.15), CosineHemisphere(NORMAL)), [0.7, 0.3])


def _in_frame(proposal, frame):
    """`(sample, pdf)` with directions written in `frame` (rows: the frame's axes)."""

    def sample(key, n):
        return proposal.sample(key, n)[0] @ frame.T

    def pdf(v):
        return proposal.pdf(v @ frame)

    return sample, pdf


# (name, proposal, frame, domain, bins, quadrature order)
CASES = [
    ("cosine_hemisphere", CosineHemisphere(NORMAL), FRAME, "hemisphere", 24, 6),
    ("uniform_hemisphere", UniformHemisphere(NORMAL), FRAME, "hemisphere", 24, 6),
    ("sphere_light", SPHERE, LIGHT_FRAME, "hemisphere", (32, 16), 6),
    ("quad_light", QUAD, jnp.eye(3), "hemisphere", (24, 48), 16),
    ("beckmann_lobe", LOBE, FRAME, "sphere", (48, 32), 6),
    ("brdf_mixture", BRDF, FRAME, "sphere", (64, 32), 6),
]
# Bonferroni over the file's χ² tests; keys are fixed, so the outcome is deterministic.
ALPHA = P_FLOOR / len(CASES)


@pytest.mark.parametrize("index", range(len(CASES)), ids=[c[0] for c in CASES])
def test_chi2(index):
    name, proposal, frame, domain, bins, order = CASES[index]
    sample, pdf = _in_frame(proposal, frame)
    key = jax.random.fold_in(jax.random.key(4321), index)
    table = chi2_table(key, sample, pdf, domain, n=N, bins=bins, quad_order=order)
    assert table.n_outside == 0, table.report()
    assert table.p_value > ALPHA, f"{name}\n{table.report()}"


def test_chi2_rejects_a_quad_density_without_its_cosine():
    # teeth: the quad's histogram is fine enough to see a missing |cos theta_l|
    sample, _ = _in_frame(QUAD, jnp.eye(3))

    def pdf(w):
        return QUAD.pdf(w) * jnp.abs(jnp.dot(QUAD.light_normal, w))

    table = chi2_table(jax.random.key(5), sample, pdf, "hemisphere", n=N, bins=(24, 48),
                       quad_order=16)
    assert table.p_value < 1e-8, table.report()


UNIFORM_W = warps.sphere_uniform(jax.random.uniform(jax.random.key(11), (1 << 18, 2)))


@jax.jit
def _pdf_and_draws(proposal, w, key):
    x, p = proposal.sample(key, 4096)
    return proposal.pdf(w), x, p, proposal.pdf(x), proposal.log_pdf(x), proposal.pdf(x[0])


@pytest.mark.parametrize("index", range(len(CASES)), ids=[c[0] for c in CASES])
def test_pdf_integrates_to_one_and_matches_sample(index):
    """∫ p dω = 1 by Monte Carlo over uniform directions (5σ, σ below 1%); the density a
    sample reports is `pdf` at it, positive; `log_pdf` is its log; one direction → scalar."""
    proposal = CASES[index][1]
    p_uniform, x, p, p_again, log_p, p_one = _pdf_and_draws(proposal, UNIFORM_W, jax.random.key(12))
    y = 4 * math.pi * np.asarray(p_uniform)
    mean, se = y.mean(), y.std(ddof=1) / math.sqrt(y.size)
    assert se < 0.01 and abs(mean - 1.0) < 5 * se, (mean, se)
    assert x.shape == (4096, 3) and p.shape == (4096,) and p_one.shape == ()
    np.testing.assert_allclose(np.linalg.norm(x, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(p, p_again, rtol=1e-9)
    assert np.all(np.asarray(p) > 0)
    np.testing.assert_allclose(log_p, np.log(p), rtol=1e-12)
    np.testing.assert_allclose(p_one, p_again[0], rtol=1e-12)


def _quad_coordinates(w):
    """Where the ray REF + t w meets QUAD's plane: `(t, a, height)`, by hand."""
    normal = np.cross(_B - _A, [0.0, 0.0, 1.0])
    denom = w @ normal
    t = np.where(denom != 0, (_A @ normal) / np.where(denom != 0, denom, 1.0), -1.0)
    y = t[:, None] * w - _A  # relative to the corner, REF at the origin
    return t, y @ (_B - _A) / np.dot(_B - _A, _B - _A), y[:, 2]


def _quad_hit(w):
    t, a, z = _quad_coordinates(w)
    return (t > 0) & (a >= 0) & (a <= 1) & (z >= 0) & (z <= 1.2)


def _near_quad_rim(w, eps=1e-9):
    """Samples on the quad's sides may round either way."""
    t, a, z = _quad_coordinates(w)
    return (t > 0) & (a >= -eps) & (a <= 1 + eps) & (z >= -eps) & (z <= 1.2 + eps)


def test_zero_density_where_the_sampler_never_goes():
    w = np.asarray(UNIFORM_W)
    margin = 1e-9
    draws = {}
    for name, proposal in (("cosine", CosineHemisphere(NORMAL)), ("uniform", UniformHemisphere(NORMAL)),
                           ("sphere", SPHERE), ("quad", QUAD)):
        p, x, *_ = _pdf_and_draws(proposal, UNIFORM_W, jax.random.key(14))  # compiled already
        draws[name] = np.asarray(p), np.asarray(x)
    cos_n = w @ NORMAL
    for name in ("cosine", "uniform"):
        p, x = draws[name]
        assert np.all(p[cos_n < -margin] == 0) and np.all(p[cos_n > margin] > 0)
        assert np.all(x @ NORMAL >= -margin)
    cos_l = w @ LIGHT_AXIS
    p, x = draws["sphere"]
    assert np.all(p[cos_l < 0.75 - margin] == 0) and np.all(p[cos_l > 0.75 + margin] > 0)
    assert np.all(x @ LIGHT_AXIS >= 0.75 - margin)
    hit = _quad_hit(w)
    p, x = draws["quad"]
    assert hit.sum() > 100 and np.all(p[~hit] == 0) and np.all(p[hit] > 0)
    assert np.all(_quad_hit(x) | _near_quad_rim(x))


# --- jaxmc.mis at shading points -------------------------------------------------------

L_E, ALBEDO = 3.0, 0.8
LIGHT_CENTER = np.array([0.5, 1.0, 2.0])
LIGHT_R = 0.6


def _sphere_irradiance_case(points, normals):
    """Reflected radiance of Lambertian points lit by the sphere light, and its closed form
    ρ L sin²θmax cos α (a sphere wholly above the horizon: Nusselt's analogue)."""
    d = LIGHT_CENTER - points
    dist = np.linalg.norm(d, axis=-1)
    axis = d / dist[:, None]
    sin2 = (LIGHT_R / dist) ** 2
    cos_alpha = np.sum(axis * normals, axis=-1)
    assert np.all(np.arccos(cos_alpha) + np.arcsin(np.sqrt(sin2)) < math.pi / 2)
    return ALBEDO * L_E * sin2 * cos_alpha


def test_mis_at_shading_points_under_vmap():
    """`jaxmc.mis` with [light, BRDF] proposals built per shading point, vmapped over four
    points, matches the closed form within 5σ at each."""
    points = np.array([[0.0, 0.0, 0.0], [0.4, 0.3, -0.2], [-0.5, 0.6, 0.1], [1.0, -0.2, 0.3]])
    normals = np.stack([_unit(v) for v in ([0, 0, 1], [0.2, 0.1, 1], [0.3, 0.3, 1], [-0.3, 0.4, 1])])
    exact = _sphere_irradiance_case(points, normals)

    def one(key, point, normal):
        light = SphereLight(LIGHT_CENTER, LIGHT_R, point)
        brdf = CosineHemisphere(normal)
        d = LIGHT_CENTER - point
        axis = d / jnp.linalg.norm(d)
        cos_max = jnp.sqrt(1 - LIGHT_R**2 / jnp.dot(d, d))

        def f(w):  # ρ/π · L · cos⁺θ on the directions that hit the light (written by hand)
            return ALBEDO / math.pi * L_E * jnp.maximum(w @ normal, 0.0) * (w @ axis >= cos_max)

        est = jaxmc.mis(key, f, [light, brdf], (512, 512))
        return est.mean, est.variance

    run = jax.jit(jax.vmap(one))
    keys = jax.random.split(jax.random.key(21), len(points))
    mean, var = map(np.asarray, run(keys, jnp.asarray(points), jnp.asarray(normals)))
    se = np.sqrt(var)
    assert np.all(se < 0.02 * exact), (se, exact)
    assert np.all(np.abs(mean - exact) < 5 * se), (mean, exact, se)


def _polygon_irradiance(vertices, normal):
    """Lambert's formula: E / L = ½ Σ_i angle(v_i, v_i+1) n·(v_i × v_i+1)/|v_i × v_i+1|."""
    v = [_unit(x) for x in vertices]
    total = 0.0
    for a, b in zip(v, v[1:] + v[:1]):
        c = np.cross(a, b)
        total += math.acos(np.clip(a @ b, -1, 1)) * (c @ normal) / np.linalg.norm(c)
    return abs(total) / 2


def test_mis_with_a_quad_light_and_a_glossy_lobe():
    """Two more pairs through `jaxmc.mis`: a quad light with cosine sampling on a
    Lambertian point (Lambert's polygon formula), and a sphere light with the Beckmann lobe
    on ∫_cone (ω·axis)² dω = 2π(1 − cos³θmax)/3."""
    point = np.array([0.1, 0.2, 0.0])
    normal = _unit([0.1, -0.2, 1.0])
    corner, eu, ev = np.array([-0.5, -0.4, 1.5]), np.array([1.2, 0.1, 0.2]), np.array([0.0, 0.9, 0.3])
    quad = QuadLight(corner, eu, ev, point)
    exact_quad = ALBEDO * L_E / math.pi * _polygon_irradiance(
        [corner - point, corner + eu - point, corner + eu + ev - point, corner + ev - point], normal)
    m = np.cross(eu, ev)

    def f_quad(w):
        t = jnp.dot(m, corner - point) / jnp.dot(m, w)
        y = point + t * w - corner
        a = jnp.dot(jnp.cross(y, ev), m) / jnp.dot(m, m)
        b = jnp.dot(jnp.cross(eu, y), m) / jnp.dot(m, m)
        hit = (t > 0) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)
        return ALBEDO / math.pi * L_E * jnp.maximum(w @ normal, 0.0) * hit

    d = LIGHT_CENTER - point
    dist = np.linalg.norm(d)
    axis, cos_max = d / dist, math.sqrt(1 - (LIGHT_R / dist) ** 2)
    sphere = SphereLight(LIGHT_CENTER, LIGHT_R, point)
    wo = _unit(2 * (axis @ normal) * normal - axis + np.array([0.2, 0.0, 0.0]))  # near the mirror
    lobe = BeckmannLobe(normal, wo, 0.3)
    exact_cone = 2 * math.pi * (1 - cos_max**3) / 3

    def f_cone(w):
        return (w @ axis) ** 2 * (w @ axis >= cos_max)

    @jax.jit
    def both(key):
        k1, k2 = jax.random.split(key)
        a = jaxmc.mis(k1, f_quad, [quad, CosineHemisphere(normal)], (2048, 2048))
        b = jaxmc.mis(k2, f_cone, [sphere, lobe], (2048, 2048), heuristic="power")
        return a.mean, a.variance, b.mean, b.variance

    mq, vq, mc, vc = map(float, both(jax.random.key(22)))
    for mean, var, exact in ((mq, vq, exact_quad), (mc, vc, exact_cone)):
        se = math.sqrt(var)
        assert se < 0.02 * exact and abs(mean - exact) < 5 * se, (mean, exact, se)


def test_batched_modules_jit_and_vmap():
    """A batch of proposals (one per shading point) built by vmap is itself vmappable, and
    gives each point the draws it gives alone."""
    normals = jnp.asarray(np.stack([_unit(v) for v in ([0, 0, 1], [1, 0, 0], [0.3, -0.4, 0.5])]))
    keys = jax.random.split(jax.random.key(3), 3)

    @jax.jit
    def run(normals, keys):
        batch = jax.vmap(CosineHemisphere)(normals)
        w, p = jax.vmap(lambda q, k: q.sample(k, 16))(batch, keys)
        alone, _ = CosineHemisphere(normals[1]).sample(keys[1], 16)
        return batch.normal, w, p, jax.vmap(lambda q, x: q.pdf(x))(batch, w), alone

    batched_normals, w, p, p_again, alone = map(np.asarray, run(normals, keys))
    assert batched_normals.shape == (3, 3) and w.shape == (3, 16, 3) and p.shape == (3, 16)
    np.testing.assert_array_less(-1e-12, np.einsum("bnk,bk->bn", w, np.asarray(normals)))
    np.testing.assert_allclose(p_again, p, rtol=1e-12)
    np.testing.assert_allclose(w[1], alone, rtol=1e-12)


def test_bad_arguments_raise():
    with pytest.raises(ValueError, match="normal"):
        CosineHemisphere(jnp.ones((2, 3)))
    with pytest.raises(ValueError, match="unit"):
        UniformHemisphere([0.0, 0.0, 2.0])
    with pytest.raises(ValueError, match="radius"):
        SphereLight([0.0, 0.0, 3.0], -1.0, [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="roughness"):
        BeckmannLobe([0.0, 0.0, 1.0], [0.0, 0.0, 1.0], 0.0)
    with pytest.raises(ValueError, match="edge"):
        QuadLight([0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="weights"):
        DirectionMixture([CosineHemisphere([0.0, 0.0, 1.0])] * 2, [0.7, 0.7])
    with pytest.raises(TypeError, match="components"):
        DirectionMixture(CosineHemisphere([0.0, 0.0, 1.0]), [1.0])
    with pytest.raises(ValueError, match="`w`"):
        CosineHemisphere([0.0, 0.0, 1.0]).pdf(jnp.ones((4, 2)))
