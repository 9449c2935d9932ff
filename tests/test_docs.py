"""The documentation's examples run as a new user runs them: each page's python blocks in
order, in a fresh interpreter with JAX's defaults (float32). Only compilation differs: the
tests' fast-compiling flags (`helpers.SUBPROCESS_XLA_FLAGS`) and the run's compilation
cache, as the notebooks' tests compile (compilation is most of a page's time; the pages
check that the examples run and raise no reliability warning, not their digits)."""

import os
import pathlib
import re
import subprocess
import sys

import pytest

from .helpers import subprocess_xla_flags


DOCS = pathlib.Path(__file__).resolve().parents[1] / "docs"
# Pages whose blocks are fragments of a setting a test machine lacks: several hosts
# (`jax.distributed`) and a user's own mesh.
FRAGMENTS = {"guide/devices.md"}
PAGES = sorted(str(p.relative_to(DOCS)) for p in DOCS.rglob("*.md")
               if "```python" in p.read_text(encoding="utf-8"))


@pytest.mark.parametrize("page", [p for p in PAGES if p not in FRAGMENTS])
def test_a_pages_examples_run(page, tmp_path):
    text = (DOCS / page).read_text(encoding="utf-8")
    code = "\n".join(re.findall(r"```python\n(.*?)```", text, re.S))
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    env.update(XLA_FLAGS=subprocess_xla_flags(),
               JAX_COMPILATION_CACHE_DIR=os.environ["JAXMC_TEST_XLA_CACHE"],
               JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
               JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0")
    # (In a temporary folder: an example may write a file, and JAX's cache goes there too.)
    code = code.replace("/tmp/jax_cache", str(tmp_path / "jax_cache"))
    # (A reliability warning in an example would greet a newcomer: it fails the page.)
    strict = "import warnings, jaxmc\nwarnings.simplefilter('error', jaxmc.ReliabilityWarning)\n"
    run = subprocess.run([sys.executable, "-c", strict + code], capture_output=True, text=True,
                         env=env, cwd=tmp_path, timeout=600, check=False)
    assert run.returncode == 0, run.stderr[-3000:]


def test_the_guide_pages_are_found():
    assert {"guide/getting-started.md", "guide/faq.md", "guide/choosing.md"} <= set(PAGES)
