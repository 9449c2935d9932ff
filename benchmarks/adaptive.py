"""Adaptive integration: jaxmc's fitted densities against vegas 6.x, side by side.

Same integrands, same evaluation budgets, closed-form reference values. For each
problem and method we measure, in steady state (compile time apart):

- `rel_sd`: per-sample relative standard deviation after adaptation,
  $\\sqrt{n \\cdot \\mathrm{Var}}/I$ of the last adaptive iteration (vegas: its last
  iteration; jaxmc `Grid+`: the last VEGAS+ iteration; `GM`: the last round of
  `adapt` with a GaussianMixture);
- `t_1e-3`: time to a relative error of 1e-3, *projected* from the measured
  adaptation time plus $(\\mathrm{rel\\_sd}/10^{-3})^2$ samples at the measured
  steady-state cost per sample;
- `err@T`: the relative error reachable in vegas's projected time `T` (equal wall
  time), projected the same way;
- `|z|`: |estimate - I| / stderr of the adaptive run (a sanity check).

Timings are wall-clock on a shared machine and noisy, so each is the median of
`TIMED_REPEATS` runs (both libraries, same count).
"""

from __future__ import annotations

import math
import statistics

import jax
import jax.numpy as jnp

from . import problems
from ._harness import Context, Result, markdown_table, optional_import, time_call
from .problems import Problem


TITLE = "Adaptive integration against vegas"

TOL = 1e-3
GRID_BINS = 256  # per axis (vegas: up to 1000; 256 measured best for jaxmc's rule here)
GM_COMPONENTS = 8  # for every problem: no knowledge of the number of modes
# Capacity of a Partition: one cell per this many evaluations of a round (at least 4).
PARTITION_SAMPLES_PER_CELL = 5
PARTITION_MAX_D = 4  # a partition needs ~h^(1-d) cells at resolution h: low dimensions only
FLOW_STEPS_PER_BATCH = 8  # Adam steps on each evaluated batch (reweighted, forward KL)
# |estimate - I| / stderr above which a run counts as biased (its variance is not trusted).
MAX_Z = 5.0
TIMED_REPEATS = 7  # timed runs after the compiling one; times are their median
FLOW_TIMED_REPEATS = 2
# `--quick` runs are mostly compiles (~3 s per Grid+ or Partition run, ~10 s per GM, ~15 s per
# Flow plus ~10 s of training per run): they take three problems, fit GM to two and no flow.
QUICK_GM = ("two Gaussians (1/3, 2/3)", "i-flow annulus d=2")


def _problems(quick: bool) -> list[Problem]:
    if quick:
        return [
            problems.vegas_narrow_gaussian(),
            problems.diagonal_gaussians("two Gaussians (1/3, 2/3)", 4, [1 / 3, 2 / 3]),
            problems.iflow_annulus(),
        ]
    dims = (2, 4, 8, 16)
    return [
        problems.vegas_narrow_gaussian(),
        problems.diagonal_gaussians("two Gaussians (1/3, 2/3)", 4, [1 / 3, 2 / 3]),
        problems.diagonal_gaussians("three Gaussians (0.23, 0.39, 0.74)", 6, [0.23, 0.39, 0.74]),
        problems.vegas_ridge(),
        *(problems.iflow_gaussian(d) for d in dims),
        *(problems.iflow_camel(d) for d in dims),
        problems.iflow_annulus(),
    ]


# ----------------------------------------------------------------------------
# Runners. Each returns a dict with rel_sd, t_adapt, t_per_sample, compile, z, evals.


def _run_vegas(vegas, problem, iterations, n, repeats):
    """`repeats` runs of vegas (at least one), seeded 0, 1, ...; the last one's result counts."""
    import gvar  # vegas's dependency; vegas >= 6 draws from `gvar.RNG`, not `np.random`

    fb = vegas.lbatchintegrand(problem.numpy_f)
    bounds = list(zip(problem.lo, problem.hi))
    seeds = iter(range(max(repeats, 1)))

    def one_run():
        gvar.ranseed(next(seeds))
        return vegas.Integrator(bounds)(fb, nitn=iterations, neval=n)

    # vegas does not compile: every run counts, the first included.
    timing = time_call(one_run, repeats=max(repeats, 1) - 1)
    t = statistics.median(timing.seconds)
    result = timing.output
    last = result.itn_results[-1]
    n_last = result.sum_neval / iterations
    exact = problem.exact
    return dict(
        rel_sd=float(last.sdev * math.sqrt(n_last) / exact),
        t_adapt=t,
        t_per_sample=t / result.sum_neval,
        compile=0.0,
        z=float(abs(result.mean - exact) / result.sdev),
        evals=int(result.sum_neval),
        q=float(result.Q),
    )


def _measured(est, variance, n_var, problem, t, first, evals, q=float("nan")):
    """The runners' common record: `variance` of the mean of `n_var` evaluations."""
    exact = problem.exact
    return dict(
        rel_sd=math.sqrt(variance * n_var) / exact,
        t_adapt=t,
        t_per_sample=t / evals,
        compile=first - t,
        z=float(abs(est.mean - exact) / est.stderr),
        evals=evals,
        q=q,
    )


def _run_timed(problem, run, n, repeats, evals):
    """Time the jitted `run(key) -> Combined`; `rel_sd` from its last round of `n` evaluations."""
    timing = time_call(lambda: run(jax.random.key(0)), repeats=repeats)
    est = timing.output
    variance = float(est.parts.variance[-1])
    return _measured(
        est, variance, n, problem, timing.median_s, timing.first_s, evals, float(est.q)
    )


def _run_grid(problem, iterations, n, repeats, bins=GRID_BINS):
    """VEGAS+: a `Grid` with adaptive stratification, first half of the iterations as warm-up."""
    from jaxmc.fit import adapt
    from jaxmc.proposals import Grid

    lo, hi = jnp.asarray(problem.lo), jnp.asarray(problem.hi)

    @jax.jit
    def run(key):
        grid = Grid(lo, hi, bins)
        warm = max(1, iterations // 2)
        est, _ = adapt(
            key, problem.jax_f, grid, iterations=iterations, n_per_iteration=n, warmup=warm,
            stratify=True,
        )
        return est

    return _run_timed(problem, run, n, repeats, iterations * n)


def _run_partition(problem, iterations, n, repeats):
    """MISER-like stratified sampling on a `Partition` of `n // PARTITION_SAMPLES_PER_CELL` cells.

    The first half of the iterations are warm-up, as for `Grid+`.
    """
    from jaxmc.fit import adapt
    from jaxmc.proposals import Partition

    lo, hi = jnp.asarray(problem.lo), jnp.asarray(problem.hi)
    cells = n // PARTITION_SAMPLES_PER_CELL

    @jax.jit
    def run(key):
        est, _ = adapt(
            key, problem.jax_f, Partition(lo, hi, cells), iterations=iterations, n_per_iteration=n,
            warmup=max(1, iterations // 2),
        )
        return est

    return _run_timed(problem, run, n, repeats, iterations * n)


def _run_gm(problem, iterations, n, repeats, components=GM_COMPONENTS):
    """A GaussianMixture started from a VEGAS+ grid's importance-weighted samples.

    Budget split (10 iterations): 4 rounds of VEGAS+ on a `Grid`, one batch of
    `n` samples from it whose weights |f|/p seed the mixture by weighted EM
    (`GaussianMixture.from_samples`: separated modes each get a component),
    then 5 rounds of `adapt` (32 BFGS steps per round on the round's samples),
    the first 2 as warm-up.
    """
    from jaxmc.fit import adapt
    from jaxmc.proposals import GaussianMixture, Grid

    lo, hi = jnp.asarray(problem.lo), jnp.asarray(problem.hi)
    grid_rounds = max(1, 2 * iterations // 5)
    gm_rounds = iterations - grid_rounds - 1
    if gm_rounds < 2:
        raise ValueError(f"the GM runner needs at least 5 iterations, got {iterations}.")

    @jax.jit
    def run(key):
        k_grid, k_seed, k_gm = jax.random.split(key, 3)
        _, grid = adapt(
            k_grid, problem.jax_f, Grid(lo, hi, GRID_BINS), iterations=grid_rounds,
            n_per_iteration=n, stratify=True,
        )
        x, p = grid.sample(k_seed, n)
        weights = jnp.abs(jax.vmap(problem.jax_f)(x)) / p
        gm = GaussianMixture.from_samples(x, weights, lo, hi, components)
        est, _ = adapt(
            k_gm, problem.jax_f, gm, iterations=gm_rounds, n_per_iteration=n, warmup=gm_rounds // 2
        )
        return est

    return _run_timed(problem, run, n, repeats, iterations * n)


def _run_flow(problem, iterations, n, repeats, replicas=8):
    r"""A `Flow` trained by Adam on the forward KL, then integrated by scrambled Sobol' in latent space.

    Budget: `(iterations - 1) * n` evaluations for training, in batches of
    `n / 10` each reused (reweighted) for `FLOW_STEPS_PER_BATCH` Adam steps, a
    tenth of each batch drawn uniformly (`defensive`), and at most `n` for the
    final estimate, as vegas's iterations. The
    final estimate is $\int_{[0,1]^d} f(T(u)) / p(T(u))\, du$ by `randomized_qmc`
    (`replicas` scrambles of $2^m \le n/\text{replicas}$ points), the flow's
    analogue of vegas's stratification; `iid` is the same flow sampled i.i.d.
    """
    import optax
    import optimistix as optx

    import jaxmc
    from jaxmc.proposals import Flow

    lo, hi = jnp.asarray(problem.lo), jnp.asarray(problem.hi)
    d = problem.d
    batch = max(256, n // 10)
    steps = (iterations - 1) * n // batch * FLOW_STEPS_PER_BATCH
    m = 2 ** int(math.log2(n // replicas))
    solver = optx.OptaxMinimiser(
        optax.adam(optax.cosine_decay_schedule(1e-2, steps)), rtol=0.0, atol=0.0
    )

    @jax.jit
    def run(key):
        k_init, k_fit, k_qmc, k_iid = jax.random.split(key, 4)
        fitted = jaxmc.fit.fit(
            k_fit,
            problem.jax_f,
            Flow(k_init, lo, hi),
            batch,
            solver=solver,
            max_steps=steps,
            resample=True,
            steps_per_batch=FLOW_STEPS_PER_BATCH,
            objective="kl",
        ).proposal

        def weight(u):
            x, log_p = fitted.forward(u)
            return problem.jax_f(x) * jnp.exp(-log_p)

        zeros, ones = jnp.zeros(d), jnp.ones(d)
        qmc = jaxmc.randomized_qmc(k_qmc, weight, zeros, ones, m, replicas=replicas)
        iid = jaxmc.importance(k_iid, problem.jax_f, fitted, m * replicas)
        return qmc, iid

    timing = time_call(lambda: run(jax.random.key(0)), repeats=repeats)
    qmc, iid = timing.output
    t, first = timing.median_s, timing.first_s
    n_final = m * replicas
    evals = steps // FLOW_STEPS_PER_BATCH * batch + n_final
    return {
        label: _measured(est, float(est.variance), n_final, problem, t, first, evals)
        for label, est in (("jaxmc Flow+QMC", qmc), ("jaxmc Flow (iid)", iid))
    }


def _time_to_tol(r):
    return r["t_adapt"] + (r["rel_sd"] / TOL) ** 2 * r["t_per_sample"]


def _err_at(r, budget_s):
    left = budget_s - r["t_adapt"]
    if left <= 0 or not math.isfinite(r["rel_sd"]):
        return float("inf")
    return r["rel_sd"] / math.sqrt(left / r["t_per_sample"])


def run(ctx: Context) -> Result:
    vegas = optional_import("vegas")
    quick = ctx.quick
    iterations = 10
    n = 5_000 if quick else 20_000
    # Timed repeats (median): the Flow runner takes a minute a run, the others well under one.
    repeats = 1 if quick else TIMED_REPEATS
    flow_repeats = FLOW_TIMED_REPEATS  # full runs only
    header = [
        "integrand",
        "d",
        "method",
        "evals",
        "rel_sd",
        "t_adapt s",
        "compile s",
        "t_1e-3 s",
        "err@T",
        "\\|z\\|",
        "Q",
        "var ratio vs vegas",
    ]
    rows, data = [], {"n_per_iteration": n, "iterations": iterations, "cases": {}}
    if vegas is None:
        ctx.log("vegas not installed (pip install vegas): comparison skipped, jaxmc only")
    for problem in _problems(quick):
        ctx.log(f"{problem.name} (d={problem.d})")
        results = {}
        if vegas is not None:
            results["vegas"] = _run_vegas(vegas, problem, iterations, n, repeats)
        results["jaxmc Grid+"] = _run_grid(problem, iterations, n, repeats)
        if problem.d <= PARTITION_MAX_D:
            results["jaxmc Partition"] = _run_partition(problem, iterations, n, repeats)
        fitted = not problem.separable or problem.d >= 8
        if fitted and (not quick or problem.name in QUICK_GM):
            results["jaxmc GM"] = _run_gm(problem, iterations, n, repeats)
        if fitted and not quick:
            results.update(_run_flow(problem, iterations, n, flow_repeats))
        t_ref = _time_to_tol(results["vegas"]) if "vegas" in results else None
        # A run whose estimate is off by > 5 stderr (e.g. a density locked onto one of
        # two peaks) has a meaningless variance: no ratio, and it is flagged.
        for r in results.values():
            r["biased"] = not (r["rel_sd"] > 0 and r["z"] <= MAX_Z)
        for method, r in results.items():
            r["t_to_tol"] = _time_to_tol(r)
            r["err_at_T"] = _err_at(r, t_ref) if t_ref is not None else float("nan")
            ratio = (
                (results["vegas"]["rel_sd"] / r["rel_sd"]) ** 2
                if "vegas" in results and not r["biased"] and not results["vegas"]["biased"]
                else float("nan")
            )
            r["var_ratio_vs_vegas"] = ratio
            rows.append(
                [
                    problem.name,
                    problem.d,
                    method,
                    r["evals"],
                    r["rel_sd"],
                    r["t_adapt"],
                    r["compile"],
                    r["t_to_tol"],
                    r["err_at_T"],
                    r["z"],
                    r["q"],
                    "biased" if r["biased"] else ratio,
                ]
            )
        data["cases"][problem.name] = results
    notes = (
        f"\n\n{iterations} iterations of up to {n} evaluations each (vegas: `neval={n}`; jaxmc "
        f"`Grid+`: `adapt(..., stratify=True)`, {GRID_BINS} bins per axis, first half of the "
        "iterations as warm-up; jaxmc `GM`: a GaussianMixture of "
        f"{GM_COMPONENTS} components seeded by weighted EM on importance-weighted samples of a "
        "VEGAS+ grid (4 rounds of the grid, 1 batch to seed, 5 rounds of `adapt` with 32 BFGS "
        "steps per round on the round's own samples); jaxmc `Partition` (d <= "
        f"{PARTITION_MAX_D}): `adapt` on a `Partition` of n/{PARTITION_SAMPLES_PER_CELL} cells, "
        "stratified over its cells (MISER-like), first half of the iterations as warm-up. "
        "`rel_sd` is per sample, from the last round; `t_1e-3` and `err@T` are projections from "
        "the measured steady-state times (T = vegas's `t_1e-3`); `var ratio` = (vegas rel_sd / "
        "method rel_sd)^2, i.e. variance per evaluation relative to vegas (> 1 is better than "
        f"vegas). Times are medians of {repeats} timed runs "
        f"({'' if quick else f'{flow_repeats} for the flows; '}jaxmc's after a compiling one); "
        "wall-clock times on a shared 2-core machine are noisy. "
        "`biased`: |z| > 5 (or a zero variance), so the run's variance means nothing: the "
        "density missed part of the integrand. `Flow+QMC`: a `Flow` trained by Adam on the "
        f"forward KL with 90% of the budget ({FLOW_STEPS_PER_BATCH} steps per evaluated batch), "
        "then integrated by 8 scrambled Sobol' replicas in its latent space (the flow's analogue "
        "of vegas's stratification); `Flow (iid)`: the same flow sampled i.i.d.; their `t_1e-3` "
        "uses the run's time per evaluation, training included."
    )
    if quick:
        notes += (
            f" Quick run: `GM` only on {' and '.join(QUICK_GM)}, no flows (the full run fits "
            "both to every problem that is not separable or has d >= 8)."
        )
    if vegas is None:
        notes += " vegas was not installed: no comparison."
    md = markdown_table(header, rows) + notes
    return Result(markdown=md, data=data)
