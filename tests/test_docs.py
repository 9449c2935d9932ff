"""The documentation's examples run as a new user runs them: each page's python blocks in
order, in a fresh interpreter with JAX's defaults (float32)."""

import os
import pathlib
import re
import subprocess
import sys

import pytest


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
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_ENABLE_X64")}
    # (In a temporary folder: an example may write a file, and JAX's cache goes there too.)
    code = code.replace("/tmp/jax_cache", str(tmp_path / "jax_cache"))
    # (A reliability warning in an example would greet a newcomer: it fails the page.)
    strict = "import warnings, jaxmc\nwarnings.simplefilter('error', jaxmc.ReliabilityWarning)\n"
    run = subprocess.run([sys.executable, "-c", strict + code], capture_output=True, text=True,
                         env=env, cwd=tmp_path, timeout=600, check=False)
    assert run.returncode == 0, run.stderr[-3000:]


def test_the_guide_pages_are_found():
    assert {"guide/getting-started.md", "guide/faq.md", "guide/choosing.md"} <= set(PAGES)
