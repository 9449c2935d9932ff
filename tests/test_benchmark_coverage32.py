"""The float32 coverage benchmark: its closed forms are right, and its rule judges."""

import jax
import jax.numpy as jnp

import benchmarks
import jaxmc
from benchmarks import coverage32
from benchmarks._harness import Context


def test_the_closed_forms_match_float64_integrals():
    # (The tests run in float64.) A wrong exact value would make the benchmark report
    # misses that are not there, or hide some.
    for case in coverage32.cases():
        est = jaxmc.integrate(jax.random.key(0), case.f, jnp.asarray(case.lo),
                              jnp.asarray(case.hi), n=2**17)
        assert abs(float(est.mean) - case.exact) < 6 * float(est.stderr) + 1e-12, case.name


def test_a_case_is_measured_in_float32_and_judged(tmp_path):
    smooth = [c for c in coverage32.cases() if c.name.startswith("exp(")][0]
    small = coverage32.Case(smooth.name, smooth.f, smooth.lo, smooth.hi, smooth.exact, 2**12)
    with jax.enable_x64(False):
        entry = coverage32.measure(Context(quick=False, out=tmp_path), small, keys=8)
    assert entry["keys"] == 8 and entry["passes"]
    assert entry["max_unflagged_z"] <= coverage32.MAX_UNFLAGGED_Z
    assert "coverage32" in benchmarks.SUITES and "coverage32" in benchmarks.FULL_ONLY
