r"""`jaxmc.integrate(method="auto")` against vegas 6.x and `scipy.integrate.qmc_quad`.

A broad set of integrands with closed-form values (`problems`): Genz's six
families at d = 2 … 16, vegas's and i-flow's peaked cases, and shapes users
bring (a correlated Gaussian posterior, a resonance off the axes, integrable
singularities, indicators of a ball and of a half-space; vegas's ridge of 1000
Gaussians is left to the adaptive suite: vmapped over jaxmc's default chunk of
2^18 points it needs ~8 GB). For each case and
budget N (integrand evaluations) the three libraries run side by side, in
float64, on `SEEDS` independent seeds each:

- jaxmc: `integrate(key, f, lo, hi, n=N, method=JAXMC_METHOD)`, key
  `jax.random.key(seed)`; the first call of each (case, N) compiles and is
  timed apart.
- vegas: the tutorial's two-step protocol (adapt, discard, then integrate):
  `integ(f, nitn=10, neval=N/40)` whose result is discarded, then
  `integ(f, nitn=10, neval=3N/40)` (adaptation left on, vegas's default), a
  `vegas.lbatchintegrand` on NumPy, seeded with `gvar.ranseed(seed)`. A
  quarter of the budget trains the map, as jaxmc's adaptive method does.
- SciPy: `qmc_quad(f, lo, hi, n_estimates=8, n_points=m, qrng=Sobol(d,
  rng=default_rng(seed)))` (8 independent scrambles of Sobol'), with
  $m = 2^{\mathrm{round}(\log_2(N/8))}$: Sobol' points keep their balance only in
  powers of two (SciPy warns otherwise), so its budget is 1.31 N at N = 1e5 and
  1.05 N at 1e6. Efficiency (below) charges the extra points to its time.

Per (case, N) and library: `relerr`, the RMS over seeds of (estimate − I)/I;
`ms`, the median steady-state wall time of one call, the smaller of two passes (every
seed after the compiling first call, then `RETIME_SEEDS` of them again once all three
libraries have run: a transient slowdown of the machine does not decide a ratio; on a
2-core machine jaxmc's calls, which use every core, read 0.48-2.9x from one pass to the
other with the same estimates, and 0.35-2.5x between runs, vegas's 0.9-1.15x); efficiency
$1/(\mathrm{relerr}^2 \cdot t)$; `cov`, the share of seeds whose interval of
nominal level 0.954 holds I: |estimate − I| ≤ 2 stderr for a normal error bar,
$t_{0.977,\nu}$ stderr for one with $\nu$ degrees of freedom (the spread of
$\nu + 1$ replicas: jaxmc's `Estimate.dof`, $\nu = 7$ for SciPy's 8 scrambles),
as `Estimate.interval(0.954)` gives; `ratio`,
jaxmc's efficiency over the better of vegas's and SciPy's (> 1: jaxmc ahead).
`JAXMC_METHOD` (environment variable of the same name, default "auto") runs
the same comparison for another method of `integrate`.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import os
import statistics
import time
import warnings
from collections.abc import Callable

import jax
import numpy as np

from . import problems, validation
from ._harness import (
    Context,
    Result,
    compiled_programs,
    markdown_table,
    normal_equivalent,
    optional_import,
    pyplot,
    time_call,
)
from .problems import Problem


TITLE = "integrate(method='auto') against vegas and scipy.integrate.qmc_quad"

JAXMC_METHOD = os.environ.get("JAXMC_METHOD", "auto")
VEGAS_NITN = 10  # iterations per step, as in vegas's tutorial
VEGAS_WARMUP_SHARE = 0.25  # share of the budget for the discarded training step
SCIPY_ESTIMATES = 8  # qmc_quad's default number of scrambles
COVERAGE_SIGMAS = 2.0
# Seeds per (case, N): a ratio of efficiencies from k seeds is uncertain by a factor of about
# exp(2 / sqrt(k)) (relerr^2 from few samples): 1.9 at 10, 1.6 at 20, 1.4 at 40 (~20 min a run).
SEEDS = 40
QUICK_SEEDS = 5
RETIME_SEEDS = 20  # seeds timed again in the second pass (`_retime`)
JIT_SEEDS = 10  # seeds timed under jax.jit (after its compiling first call)
LIBRARIES = ("jaxmc", "vegas", "scipy")


@dataclasses.dataclass(frozen=True)
class Case:
    problem: Problem
    half: str = "tuning"  # "tuning" (the cases `auto` was developed on) or "validation"
    finite_variance: bool = True  # infinite-variance cases are left out of the coverage summary


def _cases(quick: bool) -> list[Case]:
    if quick:
        # One smooth, two peaked and one correlated case, two of each half.
        return [Case(problems.genz_oscillatory(8), "validation"),
                Case(problems.vegas_narrow_gaussian()),
                Case(problems.iflow_camel(4), "validation"),
                Case(problems.correlated_gaussian(5))]
    # The suite's cases in turn go to the tuning half (the cases `auto` was developed on)
    # and the validation half, which also holds kinds the tuning half lacks (`validation`).
    genz = [
        family(d)
        for family in (
            problems.genz_oscillatory,
            problems.genz_product_peak,
            problems.genz_corner_peak,
            problems.genz_gaussian,
            problems.genz_continuous,
            problems.genz_discontinuous,
        )
        for d in (2, 8, 16)
    ]
    peaked = [
        problems.vegas_narrow_gaussian(),
        problems.diagonal_gaussians("two Gaussians (1/3, 2/3)", 4, [1 / 3, 2 / 3]),
        problems.iflow_gaussian(8),
        problems.iflow_camel(4),
        problems.iflow_camel(16),
        problems.iflow_annulus(),
    ]
    users = [
        problems.correlated_gaussian(5),
        problems.oblique_resonance(4),
        problems.oblique_resonance(12),
        problems.power_singularity(6, 1 / 3),
        problems.corner_singularity(4, 1.5),
        problems.ball_indicator(3),
        problems.ball_indicator(10),
        problems.half_space_indicator(8),
    ]
    cases = [Case(p, ("tuning", "validation")[i % 2]) for i, p in enumerate([*genz, *peaked, *users])]
    cases += [Case(p, "validation") for p in validation.cases()]
    cases.append(Case(problems.power_singularity(2, 0.5), "tuning", finite_variance=False))
    return cases


# ----------------------------------------------------------------------------
# One call per library: (estimate, stderr, evaluations, extra, degrees of freedom) for one seed.


def _jaxmc_call(problem: Problem, n: int, jit: bool = False) -> Callable[[int], tuple]:
    """jaxmc's call, eager or under `jax.jit` (the jitted function made once, so that only
    its first call compiles)."""
    import jaxmc

    f = problem.jax_f  # one bound method for every call, so the compiled loop is reused

    def integrate(key):
        return jaxmc.integrate(key, f, problem.lo, problem.hi, n=n, method=JAXMC_METHOD)

    run = jax.jit(integrate) if jit else integrate

    def call(seed):
        est = jax.block_until_ready(run(jax.random.key(seed)))
        pilot = getattr(est, "pilot", None)
        chose = str(getattr(est, "method", "?"))
        if chose == "auto" and pilot is not None:  # (traced: the choice is on the pilot)
            chose = pilot.candidates[int(pilot.choice)]
        return float(est.mean), float(est.stderr), int(est.n), chose, float(est.dof)

    return call


def _vegas_call(problem: Problem, n: int) -> Callable[[int], tuple]:
    import gvar  # vegas's dependency; vegas >= 6 draws from `gvar.RNG`, not `np.random`
    import vegas

    fb = vegas.lbatchintegrand(problem.numpy_f)
    bounds = list(zip(problem.lo, problem.hi))
    warm = VEGAS_WARMUP_SHARE * n / VEGAS_NITN
    final = (1 - VEGAS_WARMUP_SHARE) * n / VEGAS_NITN

    def call(seed):
        gvar.ranseed(seed)
        integ = vegas.Integrator(bounds)
        training = integ(fb, nitn=VEGAS_NITN, neval=warm)  # adapts the map; result discarded
        result = integ(fb, nitn=VEGAS_NITN, neval=final)
        note = f"Q={result.Q:.2f}"
        return result.mean, result.sdev, training.sum_neval + result.sum_neval, note, math.inf

    return call


def _scipy_points(n: int) -> int:
    return 2 ** round(math.log2(n / SCIPY_ESTIMATES))


def _scipy_call(problem: Problem, n: int) -> Callable[[int], tuple]:
    from scipy.integrate import qmc_quad
    from scipy.stats import qmc

    m = _scipy_points(n)
    lo, hi = np.asarray(problem.lo), np.asarray(problem.hi)

    def call(seed):
        qrng = qmc.Sobol(problem.d, rng=np.random.default_rng(seed))
        # qmc_quad passes the points as (d, n).
        res = qmc_quad(
            lambda x: problem.numpy_f(x.T), lo, hi, n_estimates=SCIPY_ESTIMATES, n_points=m,
            qrng=qrng,
        )
        # (Its standard error is the spread of the scrambles: SCIPY_ESTIMATES - 1 dof.)
        return (float(res.integral), float(res.standard_error), SCIPY_ESTIMATES * m, "",
                SCIPY_ESTIMATES - 1.0)

    return call


def _measure(call: Callable[[int], tuple], seeds: int, exact: float, compiles: bool) -> dict:
    """Run `call(seed)` for every seed; errors, coverage and times over the seeds.

    When the call `compiles`, the first one is timed apart and left out of the median.
    """
    outputs, seconds = [], []
    try:
        for seed in range(seeds):
            with compiled_programs() as compiled:
                timing = time_call(lambda s=seed: call(s), repeats=0)
            outputs.append(timing.output)
            seconds.append(timing.first_s)
            if seed == 0:
                programs = len(compiled)
    except Exception as error:  # one failing library must not hide the others' results
        return {"error": f"{type(error).__name__}: {error}"[:200]}
    means = np.array([o[0] for o in outputs], dtype=float)
    stderrs = np.array([o[1] for o in outputs], dtype=float)
    dofs = np.array([o[4] for o in outputs], dtype=float)
    relerr = float(np.sqrt(np.mean(((means - exact) / exact) ** 2)))
    steady = seconds[1:] if compiles and len(seconds) > 1 else seconds
    t = statistics.median(steady)
    return {
        "relerr": relerr,
        "rel_stderr": float(np.sqrt(np.mean(stderrs**2)) / abs(exact)),
        "seconds": t,
        "first_s": seconds[0],
        "programs": programs,
        "efficiency": 1 / (relerr**2 * t) if relerr > 0 else math.inf,
        "coverage": float(np.mean(normal_equivalent(np.abs(means - exact) / stderrs, dofs)
                                  <= COVERAGE_SIGMAS)),
        "evals": float(np.mean([o[2] for o in outputs])),
        "note": _choices([o[3] for o in outputs]),
        "means": means.tolist(),
        "stderrs": stderrs.tolist(),
        "dofs": dofs.tolist(),
    }


def _choices(chosen: list[str]) -> str:
    """The method chosen, or each with its share of the seeds where they differ."""
    counts = collections.Counter(chosen)
    if len(counts) == 1:
        return chosen[0]
    return ", ".join(f"{name} {count / len(chosen):.2f}" for name, count in counts.most_common())


def _retime(call: Callable[[int], tuple], seeds: int, result: dict) -> dict:
    """`result` (`_measure`'s) with its time the smaller median of its own pass and one more
    over seeds 1..`seeds` (compiled by now), and its efficiency anew."""
    if "seconds" not in result:
        return result
    seconds = [time_call(lambda s=seed: call(s), repeats=0).first_s for seed in range(1, 1 + seeds)]
    t = min(result["seconds"], statistics.median(seconds))
    relerr = result["relerr"]
    return {**result, "seconds": t, "seconds_passes": [result["seconds"], statistics.median(seconds)],
            "efficiency": 1 / (relerr**2 * t) if relerr > 0 else math.inf}


def _ratio(results: dict) -> float:
    ours = results["jaxmc"].get("efficiency", math.nan)
    others = [results[lib]["efficiency"] for lib in LIBRARIES[1:] if "efficiency" in results[lib]]
    if not others or not math.isfinite(ours) or max(others) <= 0:
        return math.nan
    return ours / max(others)


def _geomean(values: list[float]) -> float:
    good = [v for v in values if math.isfinite(v) and v > 0]
    return math.exp(statistics.fmean(math.log(v) for v in good)) if good else math.nan


def _plot(ctx: Context, records: list[dict], budgets: tuple[int, ...]) -> str | None:
    plt = pyplot(ctx)
    if plt is None:
        return None

    names = list(dict.fromkeys(r["case"] for r in records))
    fig, ax = plt.subplots(figsize=(max(6.0, 0.32 * len(names) + 2), 4.8))
    for i, n in enumerate(budgets):
        xs, ys = [], []
        for r in records:
            if r["n"] == n and math.isfinite(r["ratio"]) and r["ratio"] > 0:
                xs.append(names.index(r["case"]))
                ys.append(r["ratio"])
        ax.scatter(xs, ys, marker="os^"[i % 3], s=28, label=f"N = {n:.0e}", zorder=3)
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set_yscale("log")
    ax.set_xticks(range(len(names)))
    ax.set_xticklabels(names, rotation=75, ha="right", fontsize=7)
    ax.set_ylabel("efficiency ratio: jaxmc / best of vegas, scipy")
    ax.set_title(f"integrate(method={JAXMC_METHOD!r}): > 1 means jaxmc is ahead")
    ax.grid(axis="y", which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    name = f"auto{'-quick' if ctx.quick else ''}.png"
    fig.savefig(ctx.out / name, dpi=110)
    plt.close(fig)
    return name


def run(ctx: Context) -> Result:
    with jax.enable_x64(True):
        return _run(ctx)


def _measure_jit(problem: Problem, n: int, eager: dict, seeds: int) -> dict:
    """jaxmc under `jax.jit` (one jitted function per case): its first, compiling call and
    programs compiled, its median steady-state time over `seeds` seeds after the first,
    and the largest difference of its estimates from the eager ones on the same seeds,
    relative to their standard errors (0: the same numbers)."""
    if "means" not in eager:
        return {}
    call = _jaxmc_call(problem, n, jit=True)
    try:
        with compiled_programs() as compiled:
            first = time_call(lambda: call(0), repeats=0)
        seconds, differences = [], [abs(first.output[0] - eager["means"][0])
                                    / eager["stderrs"][0]]
        for seed in range(1, seeds + 1):
            timing = time_call(lambda s=seed: call(s), repeats=0)
            seconds.append(timing.first_s)
            differences.append(abs(timing.output[0] - eager["means"][seed]) / eager["stderrs"][seed])
    except Exception as error:  # (reported, as an eager failure is)
        return {"error": f"{type(error).__name__}: {error}"[:200]}
    return {"first_s": first.first_s, "programs": len(compiled),
            "seconds": statistics.median(seconds), "max_difference": max(differences)}


def _summary_line(label: str, at: list[dict]) -> tuple[str, dict]:
    """A half's (or the whole suite's) figures at one budget."""
    ratios = [r["ratio"] for r in at]
    behind = [r["case"] for r in at if math.isfinite(r["ratio"]) and r["ratio"] < 1]
    coverage = {
        lib: min((r[lib]["coverage"] for r in at if r["finite_variance"] and "coverage" in r[lib]),
                 default=math.nan)
        for lib in LIBRARIES
    }
    errors = [r["case"] for r in at if "error" in r["jaxmc"]]
    data = {"geomean_ratio": _geomean(ratios), "cases_behind": behind, "min_coverage": coverage,
            "jaxmc_errors": errors}
    text = (
        f"{label}: geometric mean of the ratio {_geomean(ratios):.3g} over "
        f"{sum(math.isfinite(v) for v in ratios)} cases; ratio < 1 in {len(behind)}"
        + (f" ({', '.join(behind)})" if behind else "")
        + "; min coverage (finite-variance cases) "
        + ", ".join(f"{lib} {coverage[lib]:.2f}" for lib in LIBRARIES)
        + (f"; jaxmc raised in {len(errors)} ({', '.join(errors)})" if errors else "")
    )
    return text, data


def _compile_line(records: list[dict]) -> tuple[str, dict]:
    """First calls (compilation included) eagerly and under `jit`, programs compiled, the
    steady-state time under `jit` against eagerly, and whether the estimates agree."""
    figures = {}
    for way, get in (("eager", lambda r: r["jaxmc"]), ("jit", lambda r: r["jaxmc"].get("jit", {}))):
        firsts = [get(r)["first_s"] for r in records if "first_s" in get(r)]
        programs = [get(r)["programs"] for r in records if "programs" in get(r)]
        if firsts:
            figures[way] = {"median_first_s": statistics.median(firsts), "max_first_s": max(firsts),
                            "median_programs": statistics.median(programs)}
    slower = [r["jaxmc"]["jit"]["seconds"] / r["jaxmc"]["seconds"] for r in records
              if "seconds" in r["jaxmc"].get("jit", {}) and "seconds" in r["jaxmc"]]
    differences = [r["jaxmc"]["jit"]["max_difference"] for r in records
                   if "max_difference" in r["jaxmc"].get("jit", {})]
    figures["jit_over_eager_max"] = max(slower, default=math.nan)
    figures["jit_eager_max_difference"] = max(differences, default=math.nan)
    text = "; ".join(
        f"{way}: first call median {v['median_first_s']:.1f} s, max {v['max_first_s']:.1f} s, "
        f"median {v['median_programs']:.0f} programs"
        for way, v in figures.items() if isinstance(v, dict)
    ) + (f"; steady-state time under jit at most {figures['jit_over_eager_max']:.2f}x eager's; "
         f"estimates under jit differ from eager ones by at most "
         f"{figures['jit_eager_max_difference']:.2g} standard errors")
    return text, figures


def _run(ctx: Context) -> Result:
    quick = ctx.quick
    budgets = (100_000,) if quick else (100_000, 1_000_000)
    seeds = QUICK_SEEDS if quick else SEEDS
    have = {
        "vegas": optional_import("vegas") is not None and optional_import("gvar") is not None,
        "scipy": optional_import("scipy.integrate") is not None,
    }
    callers = {"jaxmc": _jaxmc_call, "vegas": _vegas_call, "scipy": _scipy_call}
    records, rows = [], []
    start = time.perf_counter()
    for case in _cases(quick):
        problem = case.problem
        for n in budgets:
            results, calls = {}, {}
            for lib in LIBRARIES:
                if not have.get(lib, True):
                    results[lib] = {"error": "not installed"}
                    continue
                calls[lib] = callers[lib](problem, n)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)  # NumPy overflow at singular points
                    results[lib] = _measure(calls[lib], seeds, problem.exact, compiles=lib == "jaxmc")
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                for lib in calls:  # the second pass of times, after all three
                    results[lib] = _retime(calls[lib], min(RETIME_SEEDS, seeds - 1), results[lib])
                if "means" in results["jaxmc"]:
                    results["jaxmc"]["jit"] = _measure_jit(problem, n, results["jaxmc"],
                                                           min(JIT_SEEDS, seeds - 1))
            ratio = _ratio(results)
            jx = results["jaxmc"]
            method = jx.get("note", "error: " + jx.get("error", ""))
            record = {
                "case": problem.name, "d": problem.d, "n": n, "exact": problem.exact,
                "half": case.half, "finite_variance": case.finite_variance, "method": method,
                "ratio": ratio, **{lib: results[lib] for lib in LIBRARIES},
            }
            records.append(record)

            def cell(lib, key, scale=1.0, _results=results):
                value = _results[lib].get(key)
                return value * scale if value is not None else "err"

            jit = jx.get("jit", {})
            rows.append([
                problem.name + ("" if case.finite_variance else " (inf. var.)"),
                case.half[0].upper(), problem.d, f"{n:.0e}", method,
                *(cell(lib, "relerr") for lib in LIBRARIES),
                *(cell(lib, "seconds", 1e3) for lib in LIBRARIES),
                jit.get("seconds", math.nan) * 1e3,
                f"{jx.get('first_s', math.nan):.1f} ({jx.get('programs', '?')})",
                f"{jit.get('first_s', math.nan):.1f} ({jit.get('programs', '?')})",
                *(cell(lib, "efficiency") for lib in LIBRARIES),
                *(cell(lib, "coverage") for lib in LIBRARIES),
                "/".join(
                    f"{results[lib]['evals'] / n:.2f}" if "evals" in results[lib] else "-"
                    for lib in LIBRARIES
                ),
                ratio,
            ])
            ctx.log(
                f"{problem.name} N={n:.0e}: ratio {ratio:.3g}, method {method} "
                f"({time.perf_counter() - start:.0f} s)"
            )
    header = [
        "integrand", "half", "d", "N", "auto chose",
        "jaxmc relerr", "vegas relerr", "scipy relerr",
        "jaxmc ms", "vegas ms", "scipy ms", "jaxmc ms (jit)",
        "jaxmc 1st call s (programs)", "jaxmc 1st call s (programs), jit",
        "jaxmc eff", "vegas eff", "scipy eff",
        "jaxmc cov", "vegas cov", "scipy cov",
        "evals/N j/v/s", "ratio",
    ]
    summary, data_summary = [], {}
    for n in budgets:
        at_n = [r for r in records if r["n"] == n]
        data_summary[str(n)] = {}
        for half in ("tuning", "validation", "all"):
            at = [r for r in at_n if half == "all" or r["half"] == half]
            if not at:
                continue
            text, data = _summary_line(f"N = {n:.0e}, {half}", at)
            summary.append(f"- {text}.")
            data_summary[str(n)][half] = data
        text, data = _compile_line([r for r in at_n if "jaxmc" in r])
        summary.append(f"- N = {n:.0e}, compilation: {text}.")
        data_summary[str(n)]["compilation"] = data
    plot = _plot(ctx, records, budgets)
    notes = (
        f"jaxmc method {JAXMC_METHOD!r}; {seeds} seeds per (case, N); float64 throughout; one "
        "process, every case's programs compiled in it (no cache cleared between cases). "
        "`half`: T, the tuning half (the cases `auto` was developed on), V, the validation "
        "half (the rest of the suite's families and kinds the tuning half lacks). "
        "`relerr`: RMS over seeds of (estimate − I)/I; `ms`: median wall time of one "
        "steady-state call (jaxmc's first, compiling call apart, in `1st call s`, with the "
        "number of XLA programs it compiled), the smaller of two passes (all seeds, then "
        f"{RETIME_SEEDS} again after the three libraries ran); `ms (jit)`: jaxmc's call under "
        f"`jax.jit`, median over {JIT_SEEDS} seeds; `eff` = "
        "1/(relerr² · s); `cov`: share of seeds with |estimate − I| ≤ 2 stderr, or the "
        "Student-t quantile of the same level (0.954) for an error bar with few degrees of "
        "freedom (jaxmc's `Estimate.dof`; 7 for SciPy's 8 scrambles); `evals/N`: "
        "integrand evaluations per call over N; `ratio`: jaxmc's eff over the better of "
        "vegas's and SciPy's (> 1: jaxmc ahead); `auto chose`: the method `integrate` "
        "reports, its share of the seeds where they differ. vegas: `integ(f, nitn=10, "
        "neval=N/40)` discarded, then `integ(f, nitn=10, neval=3N/40)` (vegas's tutorial "
        "protocol; a quarter of the budget to adapt), `lbatchintegrand`, `gvar.ranseed(seed)`. "
        "SciPy: `qmc_quad` with 8 scrambled Sobol' rules of 2^round(log2(N/8)) points. With "
        f"{seeds} seeds a ratio is uncertain by a factor ~{math.exp(2 / math.sqrt(seeds)):.1f} "
        "(relerr² from few samples); wall-clock times on a shared machine are noisy."
    )
    markdown = "\n\n".join([notes, markdown_table(header, rows), "\n".join(summary)])
    data = {
        "method": JAXMC_METHOD, "seeds": seeds, "budgets": list(budgets),
        "vegas": {"nitn": VEGAS_NITN, "warmup_share": VEGAS_WARMUP_SHARE},
        "scipy": {"n_estimates": SCIPY_ESTIMATES, "n_points": {n: _scipy_points(n) for n in budgets}},
        "summary": data_summary, "cases": records,
    }
    return Result(markdown=markdown, data=data, plots=[plot] if plot else [])
