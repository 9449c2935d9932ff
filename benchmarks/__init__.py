"""jaxmc's benchmark suites, run with `python -m benchmarks`.

Each suite is a module here with `TITLE` and `run(ctx: Context) -> Result`;
`SUITES` lists them in running order.
"""

SUITES = ("throughput", "points", "convergence", "adaptive", "render")
