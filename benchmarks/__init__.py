"""jaxmc's benchmark suites, run with `python -m benchmarks`.

Each suite is a module here with `TITLE` and `run(ctx: Context) -> Result`;
`SUITES` lists them in running order. The suites share `_harness` (context,
results, the timer `time_call`) and `problems` (the integrands, each written once
for `jax.numpy` and `numpy`).
"""

SUITES = ("throughput", "points", "proposals", "convergence", "adaptive", "auto", "infinite",
          "plans", "render", "coverage", "coverage32")
# Suites that have no quick setting (their point is many seeds): `--quick` skips them.
FULL_ONLY = ("plans", "coverage", "coverage32")
