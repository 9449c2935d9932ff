import atexit
import os
import shutil
import subprocess
import sys
import tempfile


# XLA's CPU backend compiles for speed of compilation in tests: no backend optimisation
# (level 0 of 3), the elemental emitters rather than the fusion emitters, and one LLVM
# module per program. Compilation is most of the suite's time (measured on two cores: level
# 2 -> 1, 916 s -> 790 s for the suite; 1 -> 0, 16:06 -> 14:39; the emitters and the one
# module, 17:35 -> 10:01 in `.ci/run`, tests/test_integrate_auto.py and tests/test_args.py
# 230 s -> 105 s, a traced `auto` 12.0 s -> 7.8 s). No check may depend on how the compiler
# optimises (a GPU fuses differently again); the benchmarks measure the defaults. Set
# before JAX starts its backend, for this process, the xdist workers (they inherit the
# variable) and the tests' subprocesses (`helpers.subprocess_xla_flags`); subprocesses
# that set their own flags keep those. XLA aborts on a flag it does not know, so the
# emitter flags are kept only if a jaxlib started with them runs.
_LEVEL = "--xla_backend_optimization_level"
_EMITTERS = ("--xla_cpu_use_fusion_emitters=false", "--xla_cpu_parallel_codegen_split_count=1")


def _accepted(flags: str) -> bool:
    probe = "import jax, jax.numpy as jnp; jax.jit(jnp.sin)(1.0).block_until_ready()"
    env = {**os.environ, "XLA_FLAGS": flags, "JAX_PLATFORMS": "cpu"}
    run = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True)
    return run.returncode == 0


if "JAXMC_TEST_XLA_FLAGS" not in os.environ:
    _flags = f"{_LEVEL}=0"
    if _accepted(" ".join((_flags,) + _EMITTERS)):
        _flags = " ".join((_flags,) + _EMITTERS)
    os.environ["JAXMC_TEST_XLA_FLAGS"] = _flags
    if _LEVEL not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_flags}".strip()

import jax  # noqa: E402
import pytest  # noqa: E402


# One persistent compilation cache for the run, shared by its xdist workers (they inherit
# the variable from the process that loaded this file first) and removed at its exit:
# tests compile the same programs under different names and in different modules (after
# `_release_compiled_programs`); measured on tests/test_fit.py, 152 s -> 127 s. Every
# program is kept, however quick its compilation: the many small ones (eager operations
# among them) are compiled again in every module after `_release_compiled_programs`
# (measured on eight modules of small tests: 147 s -> 138 s).
if "JAXMC_TEST_XLA_CACHE" not in os.environ:
    os.environ["JAXMC_TEST_XLA_CACHE"] = tempfile.mkdtemp(prefix="jaxmc-test-xla-cache-")
    atexit.register(shutil.rmtree, os.environ["JAXMC_TEST_XLA_CACHE"], ignore_errors=True)
jax.config.update("jax_compilation_cache_dir", os.environ["JAXMC_TEST_XLA_CACHE"])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


# Tests run in float64 so that statistical checks measure the estimators, not
# float32 rounding; accuracy-sensitive float32 paths have explicit tests.
jax.config.update("jax_enable_x64", True)
# Not set, unlike optimistix: `jax_numpy_rank_promotion="raise"` (jaxmc broadcasts
# `(d,)` bounds against `(n, d)` points throughout, on purpose) and
# `jax_numpy_dtype_promotion="strict"` (integer counts and indices meet floats in
# many places). Warnings are errors: see `filterwarnings` in pyproject.toml.


# The longest tests (a notebook's kernel, two processes) start first: the workers of `-n 2`
# take tests in collection order, and a minute-long test taken last leaves the other idle.
# Whole files move, so module-scoped fixtures still run once.
_FIRST = ("test_notebooks.py", "test_multiprocess.py")


def pytest_collection_modifyitems(items):
    items.sort(key=lambda item: item.path.name not in _FIRST)  # (a stable sort)


@pytest.fixture
def key():
    """Deterministic key (seed 20261122); tests that need several split it."""
    return jax.random.key(20261122)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop JAX's compiled programs after each test module: a worker running hundreds of
    tests otherwise holds every executable it compiled (measured: 6.1 GB against 4.2 GB
    peak on four modules, no slower), and two such workers came near the machine's memory."""
    yield
    jax.clear_caches()
