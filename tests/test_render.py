"""Tests for `jaxmc.render`: unbiasedness across strategies, Veach's variance ordering,
gradients against finite differences, input errors and PNG output.

Statistics are per-plate sums of pixel radiance over several fixed keys, on
small images, so every strategy is compiled once per scene and re-run cheaply.
"""

import functools
import struct
import zlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmc.render import object_ids, render, save_png, scenes


W, H = 48, 32
SEED = 20261122

VEACH_STRATEGIES = ("light", "brdf", "mis_balance", "mis_power", "mis_one_sample")
AREA_STRATEGIES = ("light", "hemisphere_uniform", "hemisphere_cosine", "mis_one_sample")
PLATES = ("plate1", "plate2", "plate3", "plate4")  # smoothest (farthest) to roughest


@functools.cache
def _scene(name):
    return scenes.veach_mis() if name == "veach" else scenes.area_light()


@functools.cache
def _region_sums(scene_name, strategy, points="uniform", spp=8, replicas=32):
    """`(replicas, regions)` sums of pixel radiance over each region, one row per key.

    Also checks every image is finite and non-negative.
    """
    scene = _scene(scene_name)
    regions = PLATES if scene_name == "veach" else ("floor", "ball")
    ids = np.asarray(object_ids(scene, W, H))
    masks = [ids == scene.index(r) for r in regions]
    keys = jax.random.split(jax.random.key(SEED), replicas)
    rows = []
    for k in keys:
        image = np.asarray(
            render(k, scene, strategy=strategy, spp=spp, width=W, height=H, points=points)
        )
        assert image.shape == (H, W, 3)
        assert np.all(np.isfinite(image)), (strategy, points)
        assert np.all(image >= 0), (strategy, points)
        rows.append([image[m].sum() for m in masks])
    return np.asarray(rows)


def _mean_se(sums):
    return sums.mean(0), sums.std(0, ddof=1) / np.sqrt(sums.shape[0])


def _sd(sums):
    return sums.std(0, ddof=1)


def test_plates_are_visible():
    scene = _scene("veach")
    ids = np.asarray(object_ids(scene, W, H))
    for plate in PLATES:
        assert (ids == scene.index(plate)).sum() > 40, plate


@pytest.mark.parametrize("strategy", VEACH_STRATEGIES)
def test_veach_strategies_agree_in_expectation(strategy):
    """Each strategy's per-plate mean matches balance-heuristic MIS within 5 sigma."""
    ref_mean, ref_se = _mean_se(_region_sums("veach", "mis_balance"))
    mean, se = _mean_se(_region_sums("veach", strategy))
    z = np.abs(mean - ref_mean) / np.sqrt(se**2 + ref_se**2)
    if strategy == "light":
        # On the mirror-like plate 1 light sampling reaches the highlight of the big light
        # a handful of times per image set: its spread over 32 keys does not resolve that
        # tail, so a z-score there would be meaningless (this is Veach's point).
        z = z[1:]
    assert np.all(z < 5), (strategy, mean, ref_mean, z)


@pytest.mark.parametrize("strategy", ["mis_balance", "mis_power", "mis_one_sample"])
def test_mis_beats_the_worse_single_strategy_on_every_plate(strategy):
    worse = np.maximum(_sd(_region_sums("veach", "light")), _sd(_region_sums("veach", "brdf")))
    mis = _sd(_region_sums("veach", strategy))
    assert np.all(mis < worse), (strategy, mis, worse)


def test_light_sampling_wins_on_the_roughest_plate():
    light = _sd(_region_sums("veach", "light"))
    brdf = _sd(_region_sums("veach", "brdf"))
    assert light[3] < brdf[3], (light, brdf)


def test_brdf_sampling_wins_on_the_smoothest_plate():
    light = _sd(_region_sums("veach", "light"))
    brdf = _sd(_region_sums("veach", "brdf"))
    assert brdf[0] < light[0], (light, brdf)


def test_area_light_strategies_agree_in_expectation():
    # the multi-sample MIS and BRDF code paths are the same as on veach_mis, checked there
    ref_mean, ref_se = _mean_se(_region_sums("area", "light", replicas=16))
    for strategy in AREA_STRATEGIES[1:]:
        mean, se = _mean_se(_region_sums("area", strategy, replicas=16))
        z = np.abs(mean - ref_mean) / np.sqrt(se**2 + ref_se**2)
        assert np.all(z < 5), (strategy, mean, ref_mean, z)


def test_area_sampling_has_the_lowest_variance_on_the_floor():
    """Lecture eq. 15: sampling the light's area beats sampling the hemisphere."""
    sd = {
        s: _sd(_region_sums("area", s, replicas=16))[0]
        for s in ("light", "hemisphere_uniform", "hemisphere_cosine")
    }
    # (cosine weighting need not beat uniform here: much of the floor sees the light at
    # grazing angles, where cosine sampling puts few directions)
    assert 3 * sd["light"] < min(sd["hemisphere_cosine"], sd["hemisphere_uniform"]), sd


@pytest.mark.parametrize("points", ["stratified", "latin_hypercube", "halton"])
def test_point_sets_are_unbiased_and_help_area_sampling(points):
    ref_mean, ref_se = _mean_se(_region_sums("area", "light", replicas=16))
    sums = _region_sums("area", "light", points=points, replicas=16)
    mean, se = _mean_se(sums)
    assert np.all(np.abs(mean - ref_mean) < 5 * np.sqrt(se**2 + ref_se**2)), (mean, ref_mean)
    # the light's area is smooth to sample: a well-spread 2-D pattern cuts the floor's noise
    assert _sd(sums)[0] < _sd(_region_sums("area", "light", replicas=16))[0]


def _plate_mean(scene, key, plate, strategy="light"):
    image = render(key, scene, strategy=strategy, spp=8, width=W, height=H)
    mask = jnp.asarray(np.asarray(object_ids(scene, W, H)) == scene.index(plate))
    return jnp.sum(jnp.where(mask[..., None], image, 0.0)) / mask.sum()


def test_gradients_match_central_differences():
    """d(mean radiance of plate 3)/d(its roughness) and /d(radiance of light 3), same key.

    Light sampling draws directions independently of the roughness, so under common
    random numbers the estimate is smooth in both parameters and its derivative must
    match a central difference to float64 accuracy. One `grad` with respect to the
    whole scene also shows every parameter gets a finite gradient.
    """
    scene = _scene("veach")
    key = jax.random.key(SEED + 1)
    plate = scene.index("plate3") - len(scene.spheres)  # row among the quads
    light = scene.index("light3")
    f = lambda s: _plate_mean(s, key, "plate3")

    value, grads = jax.value_and_grad(f)(scene)
    assert np.isfinite(value) and value > 0
    leaves = jax.tree_util.tree_leaves(eqx.filter(grads, eqx.is_inexact_array))
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in leaves)
    g_a = grads.quads.material.roughness[plate]
    g_l = grads.spheres.material.emission[light].sum()  # all three channels move together

    def with_roughness(a):
        r = scene.quads.material.roughness
        return eqx.tree_at(lambda s: s.quads.material.roughness, scene, r.at[plate].set(a))

    def with_radiance(le):
        e = scene.spheres.material.emission
        return eqx.tree_at(lambda s: s.spheres.material.emission, scene, e.at[light].set(le))

    a0 = scene.quads.material.roughness[plate]
    l0 = scene.spheres.material.emission[light]
    ha, hl = 1e-5 * a0, 1e-4 * l0[0]
    fd_a = (f(with_roughness(a0 + ha)) - f(with_roughness(a0 - ha))) / (2 * ha)
    fd_l = (f(with_radiance(l0 + hl)) - f(with_radiance(l0 - hl))) / (2 * hl)
    assert abs(g_a) > 1.0  # roughness matters to a glossy plate
    assert g_l > 0
    np.testing.assert_allclose(g_a, fd_a, rtol=1e-4)
    np.testing.assert_allclose(g_l, fd_l, rtol=1e-6)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(strategy="path_tracing"), "strategy"),
        (dict(strategy="light", points="sobol"), "points"),
        (dict(strategy="hemisphere_uniform"), "strategy"),  # not offered by veach_mis
        (dict(strategy="light", spp=0), "spp"),
    ],
)
def test_bad_arguments_raise(kwargs, match):
    args = dict(spp=1, width=4, height=3) | kwargs
    with pytest.raises(ValueError, match=match):
        render(jax.random.key(0), _scene("veach"), **args)


def test_save_png_round_trip(tmp_path):
    image = np.zeros((5, 7, 3))
    image[..., 0] = np.linspace(0, 1, 7)[None, :]
    image[2, 3] = [0.5, 2.0, np.nan]  # clipped and blanked, not an error
    path = tmp_path / "x.png"
    save_png(path, image)
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = struct.unpack(">II", data[16:24])
    assert (width, height) == (7, 5)
    # IHDR + IDAT decode by hand: filter byte 0 then RGB rows
    idat_len = struct.unpack(">I", data[33:37])[0]
    raw = zlib.decompress(data[41 : 41 + idat_len])
    rows = np.frombuffer(raw, np.uint8).reshape(5, 1 + 7 * 3)
    assert np.all(rows[:, 0] == 0)
    pixels = rows[:, 1:].reshape(5, 7, 3)
    assert pixels[0, 0, 0] == 0 and pixels[0, -1, 0] == 255
    assert tuple(pixels[2, 3]) == (188, 255, 0)  # sRGB(0.5) = 188
    mpimg = pytest.importorskip("matplotlib.image")
    decoded = mpimg.imread(path)
    assert decoded.shape[:2] == (5, 7)
    np.testing.assert_allclose(decoded[..., :3] * 255, pixels, atol=0.5)
