"""The README's examples print what the README shows, and the README stays short."""

import os
import pathlib
import re
import subprocess
import sys


README = pathlib.Path(__file__).resolve().parents[1] / "README.md"


def test_the_readme_examples_print_what_it_shows():
    # Run as a new user runs them: a fresh interpreter, JAX's defaults (float32), the
    # python blocks in order; their output is the text blocks, in order.
    text = README.read_text(encoding="utf-8")
    code = "\n".join(re.findall(r"```python\n(.*?)```", text, re.S))
    shown = "".join(re.findall(r"```text\n(.*?)```", text, re.S))
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_ENABLE_X64")}
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                         timeout=600, check=False)
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout == shown, (run.stdout, shown)


def test_the_readme_is_short():
    words = len(README.read_text(encoding="utf-8").split())
    assert words <= 600, words
