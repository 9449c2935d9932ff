"""`integrate` with meshes: a user's mesh context, any axis names, `vmap` over sharded parameters.

The runs need several devices, so they happen in a subprocess with four host
devices. For a fixed key and n, a run's estimate is that of one device up to the
rounding of the merges; with the same number of devices it is the same bits.
"""

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from .helpers import subprocess_xla_flags


SCRIPT = """
    import json, sys
    import jax, jax.numpy as jnp, numpy as np, jaxmc
    from jax.sharding import NamedSharding, PartitionSpec as P

    jax.config.update("jax_enable_x64", True)
    assert len(jax.devices()) == 4, jax.devices()

    def f(x):
        return jnp.stack([jnp.sum(x**2), jnp.prod(jnp.cos(x))])

    key, lo, hi = jax.random.key(3), jnp.zeros(3), jnp.ones(3)
    run = dict(n=2**16, chunk=2**14, method="plain")

    def integrate(g=f, **kwargs):
        return jaxmc.integrate(key, g, lo, hi, **{**run, **kwargs})

    def numbers(est):
        return [np.asarray(est.mean).tolist(), np.asarray(est.variance).tolist(), int(est.n)]

    def scaled(method):  # jit(vmap) over parameters p: the integrals of p * f
        return jax.jit(jax.vmap(lambda p: integrate(lambda x: p * f(x), method=method).mean))

    one = jax.make_mesh((1,), ("b",), devices=jax.devices()[:1])
    x2 = jax.make_mesh((2,), ("x",))
    ab = jax.make_mesh((2, 2), ("a", "b"))
    auto4 = jax.make_mesh((4,), ("x",), axis_types=(jax.sharding.AxisType.Auto,))
    ps = jnp.array([0.5, 1.0, 2.0, 4.0])
    out = {
        "one": numbers(integrate(mesh=one)),
        "one_qmc": numbers(integrate(mesh=one, method="qmc")),
        "default": numbers(integrate()),
        "ab": numbers(integrate(mesh=ab)),
        "vmap_no_context": scaled("plain")(jax.device_put(ps, NamedSharding(x2, P("x")))).tolist(),
    }
    with jax.set_mesh(ab):
        out["context_ab"] = numbers(integrate())
    with jax.set_mesh(x2):
        out["context_qmc"] = numbers(integrate(method="qmc"))
        # An array argument under the context mesh is typed on it; the integrand captures it.
        out["context_jit"] = jax.jit(lambda p: integrate(lambda x: p * f(x)).mean)(jnp.float64(2.0)).tolist()
        sharded = jax.device_put(ps, NamedSharding(x2, P("x")))
        out["vmap"] = scaled("plain")(sharded).tolist()
        out["vmap_qmc"] = scaled("qmc")(sharded).tolist()
        try:
            integrate(mesh=ab)
        except ValueError as error:
            out["other_mesh"] = str(error)
    # Inside a user's shard_map, each device integrates its own parameter on its own.
    per_device = jax.shard_map(
        lambda p: integrate(lambda x: p[0] * f(x), nonfinite="drop").mean[None],
        mesh=auto4, in_specs=P("x"), out_specs=P("x"),
    )
    out["shard_map"] = jax.jit(per_device)(ps).tolist()
    integrate(progress=True)
    print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def results():
    env = {**os.environ, "JAX_PLATFORMS": "cpu",
           "XLA_FLAGS": subprocess_xla_flags(devices=4)}
    done = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(SCRIPT)],
        capture_output=True, text=True, env=env, timeout=600,
    )
    assert done.returncode == 0, done.stderr[-4000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    out["stderr"] = done.stderr
    return out


def _close(a, b, rtol=1e-12):
    np.testing.assert_allclose(np.asarray(a, float), np.asarray(b, float), rtol=rtol, atol=0)


def test_any_axis_names_give_the_same_bits(results):
    # Four devices laid out 2x2 as ('a', 'b'), passed or as the context mesh, run the
    # blocks of the default four-device mesh in the same places.
    assert results["ab"] == results["default"]
    assert results["context_ab"] == results["default"]


def test_devices_do_not_change_the_estimate(results):
    mean, variance, n = results["default"]
    one_mean, one_variance, one_n = results["one"]
    _close(mean, one_mean)
    _close(variance, one_variance, rtol=1e-9)
    assert n == one_n == 2**16


def test_context_mesh_with_qmc(results):
    mean, variance, n = results["context_qmc"]
    _close(mean, results["one_qmc"][0])
    _close(variance, results["one_qmc"][1], rtol=1e-9)
    assert n == results["one_qmc"][2]


def test_jit_under_context_with_captured_parameter(results):
    _close(results["context_jit"], 2.0 * np.asarray(results["one"][0]))


@pytest.mark.parametrize("case, method", [("vmap", "one"), ("vmap_qmc", "one_qmc"),
                                          ("vmap_no_context", "one")])
def test_vmap_over_sharded_parameters(results, case, method):
    # Powers of two scale every sample exactly, so p * (integral of f) is exact.
    expected = np.array([0.5, 1.0, 2.0, 4.0])[:, None] * np.asarray(results[method][0])
    _close(results[case], expected)


def test_inside_a_users_shard_map(results):
    expected = np.array([0.5, 1.0, 2.0, 4.0])[:, None] * np.asarray(results["one"][0])
    _close(results["shard_map"], expected)


def test_a_mesh_other_than_the_context_mesh_is_refused(results):
    assert "context mesh" in results["other_mesh"] and "mesh=None" in results["other_mesh"]


def test_progress_reports_once_per_step_with_several_devices(results):
    # One tqdm bar (the first device reports), closed with a newline at the whole budget.
    err = results["stderr"]
    assert err.count("0.00/65.5k") == 1 and "65.5k/65.5k" in err
