r"""Coverage: can each method's error bar be believed, and do the diagnostics say when not?

For every (method, integrand) cell, `SEEDS` independent runs at a modest budget
$n$, in float64. Each run gives $z = (\hat I - I)/\widehat{\mathrm{se}}$; an
honest Gaussian error bar gives $P(|z| \le 1) \approx 0.683$ and
$P(|z| \le 2) \approx 0.954$, and $E|z| = \sqrt{2/\pi} \approx 0.80$. An error bar with
$\nu$ degrees of freedom (`Estimate.dof`: the spread of $\nu + 1$ replicas) is read
with Student's t, as `Estimate.interval` reads it: $|z|$ is first mapped to the
normal $|z|$ of the same tail probability. Alongside,
the share of runs that `jaxmc.stats.unreliable` flags (tiny `ess`, few non-zero
values, Pareto $\hat k > 0.7$, dropped non-finite values, adaptive rounds that
disagree, an unmet tolerance).

A cell *passes* when its 2σ coverage lies in [0.9, 0.99], or when the diagnostics
flag most (> 50 %) of its runs: an error bar is either right or announced as
untrustworthy.

Methods: `uniform`, `importance` (a `Grid` adapted once per integrand by
`fit.adapt`, then fixed), `stratified` (a cubic grid, two points per cell),
`antithetic`, `randomized_qmc` (16 scrambled Sobol' replicas), `fit.adapt` with
its defaults on a fresh `Grid` (8 rounds of $n/8$), and `integrate` with
`method` = plain, qmc, adaptive and auto. Every cell is one jitted function
mapped over the seeds' keys (`lax.map` in batches, so memory stays bounded).
"""

from __future__ import annotations

import dataclasses
import math
import statistics
import time
import warnings
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from . import problems
from ._harness import Context, Result, markdown_table, normal_equivalent, pyplot
from .problems import Problem


TITLE = "Coverage of the error bars, and what the diagnostics flag"

SEEDS = 200
N = 2**14
SEED_BATCH = 25  # seeds vmapped together inside one cell's `lax.map`
ADAPT_ROUNDS = 8  # fit.adapt's rounds (n / 8 points each), for `adapt` and the fixed `importance` grid
QMC_REPLICAS = 16  # randomized_qmc's default
LEVELS = (0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 0.99)  # nominal coverages of the calibration curves
PASS_BAND = (0.9, 0.99)  # acceptable 2-sigma coverage
FLAGGED_MAJORITY = 0.5


@dataclasses.dataclass(frozen=True)
class Case:
    problem: Problem
    kind: str  # what the integrand tests, for the table
    n: int = N


def cases() -> list[Case]:
    """The integrand set: benign, peaked, discontinuous, singular, and a peak `n` misses."""
    return [
        Case(problems.genz_oscillatory(2), "benign"),
        Case(problems.product_cos(4), "benign"),
        Case(problems.genz_gaussian(8), "benign"),
        Case(problems.narrow_gaussian(2, 0.02), "peaked"),
        Case(problems.vegas_narrow_gaussian(), "peaked"),
        Case(problems.genz_discontinuous(4), "discontinuous"),
        Case(problems.half_space_indicator(8), "discontinuous"),
        Case(problems.thin_shell(3), "thin shell"),
        Case(problems.power_singularity(1, 0.5), "singular, infinite variance"),
        Case(problems.power_singularity(1, 1 / 3), "singular, finite variance"),
        Case(problems.narrow_gaussian(2, 1e-3), "missed peak", n=2**12),
    ]


# ----------------------------------------------------------------------------
# Methods: each builds, for one case, a function key -> Estimate (traced, so it maps).


def _bounds(problem: Problem):
    return jnp.asarray(problem.lo), jnp.asarray(problem.hi)


def _stratified_counts(n: int, d: int) -> tuple[int, ...]:
    """The largest cubic grid with two points per cell within `n` evaluations."""
    c = int(math.floor((n / 2) ** (1 / d) + 1e-9))
    return (c,) * d


def _adapted_grid(problem: Problem, n: int):
    """A `Grid` adapted once, by `fit.adapt`'s defaults on one budget, and then kept fixed."""
    import jaxmc

    lo, hi = _bounds(problem)
    _, grid = jaxmc.fit.adapt(
        jax.random.key(1), problem.jax_f, jaxmc.proposals.Grid(lo, hi),
        iterations=ADAPT_ROUNDS, n_per_iteration=n // ADAPT_ROUNDS,
    )
    return grid


def _method_builders() -> dict[str, Callable[[Problem, int], Callable]]:
    import jaxmc

    def box(fn):
        def build(problem, n):
            lo, hi = _bounds(problem)
            return lambda key: fn(key, problem.jax_f, lo, hi, n, problem.d)

        return build

    def importance(problem, n):
        grid = _adapted_grid(problem, n)
        return lambda key: jaxmc.importance(key, problem.jax_f, grid, n)

    def adapt(problem, n):
        lo, hi = _bounds(problem)
        grid = jaxmc.proposals.Grid(lo, hi)
        return lambda key: jaxmc.fit.adapt(
            key, problem.jax_f, grid, iterations=ADAPT_ROUNDS, n_per_iteration=n // ADAPT_ROUNDS
        )[0]

    def integrate(method):
        return box(lambda k, f, lo, hi, n, d: jaxmc.integrate(k, f, lo, hi, n=n, method=method))

    return {
        "uniform": box(lambda k, f, lo, hi, n, d: jaxmc.uniform(k, f, lo, hi, n)),
        "importance": importance,
        "stratified": box(
            lambda k, f, lo, hi, n, d: jaxmc.stratified(k, f, lo, hi, _stratified_counts(n, d))
        ),
        "antithetic": box(lambda k, f, lo, hi, n, d: jaxmc.antithetic(k, f, lo, hi, n)),
        "randomized_qmc": box(
            lambda k, f, lo, hi, n, d: jaxmc.randomized_qmc(
                k, f, lo, hi, n // QMC_REPLICAS, replicas=QMC_REPLICAS
            )
        ),
        "fit.adapt": adapt,
        **{f"integrate {m}": integrate(m) for m in ("plain", "qmc", "adaptive", "auto")},
    }


METHODS = tuple(
    ["uniform", "importance", "stratified", "antithetic", "randomized_qmc", "fit.adapt"]
    + [f"integrate {m}" for m in ("plain", "qmc", "adaptive", "auto")]
)


# ----------------------------------------------------------------------------
# One cell: run every seed, keep what the summary needs.


def _observe(est) -> dict[str, jax.Array]:
    """The per-run figures: estimate, error bar, the flag and the diagnostics behind it."""
    import jaxmc

    as_float = lambda a: jnp.asarray(a, jnp.float64)
    return {
        "mean": est.mean,
        "stderr": est.stderr,
        "dof": as_float(est.dof),
        "n": as_float(est.n),
        "flagged": as_float(jaxmc.stats.unreliable(est)),
        "ess": as_float(est.ess),
        "pareto_k": as_float(est.pareto_k),
        "n_nonzero": as_float(est.n_nonzero),
        # Adaptive rounds' agreement, where there are rounds (`fit.adapt`'s Combined).
        "q": as_float(getattr(est, "q", jnp.nan)),
    }


def run_cell(method: str, case: Case, seeds: int) -> tuple[dict[str, np.ndarray], list[str]]:
    """Every seed's `_observe` figures for one (method, case): one jitted map over the keys,
    or, if the method does not trace under `vmap`, a loop of single calls.

    Also returns the warnings raised while setting the method up (`importance`'s grid
    is adapted once, outside `jit`, and may warn that its own rounds were unreliable).
    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        call = _method_builders()[method](case.problem, case.n)
    setup = [f"{type(w.message).__name__}: {w.message}" for w in caught]
    keys = jax.random.split(jax.random.key(0), seeds)
    try:
        mapped = jax.jit(
            lambda ks: jax.lax.map(lambda k: _observe(call(k)), ks, batch_size=SEED_BATCH)
        )
        out = jax.block_until_ready(mapped(keys))
    except Exception as error:  # a method that does not vmap still gets measured
        print(f"  {method}: not mappable ({type(error).__name__}), looping", flush=True)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # ReliabilityWarning per seed: the flag records it
            runs = [_observe(call(k)) for k in keys]
        out = jax.tree.map(lambda *xs: jnp.stack(xs), *runs)
    return {name: np.asarray(value, dtype=float) for name, value in out.items()}, setup


def _normal_quantile(level: float) -> float:
    """$z$ with $P(|Z| \\le z) = $ `level` for a standard normal $Z$."""
    return statistics.NormalDist().inv_cdf(0.5 + level / 2)


def summarise(method: str, case: Case, runs: dict[str, np.ndarray]) -> dict:
    """Coverage at 1 and 2 sigma and at `LEVELS`, mean |z|, the flagged share and the verdict."""
    with np.errstate(divide="ignore", invalid="ignore"):  # a zero error bar: |z| = inf
        z = (runs["mean"] - case.problem.exact) / runs["stderr"]
    # An error bar with few degrees of freedom (replicas) is read with Student's t: every
    # level below is the coverage of `Estimate.interval` at that level.
    absz = normal_equivalent(np.abs(z), runs["dof"])
    cov1, cov2 = float(np.mean(absz <= 1)), float(np.mean(absz <= 2))
    flagged = float(np.mean(runs["flagged"]))
    in_band = PASS_BAND[0] <= cov2 <= PASS_BAND[1]
    n = runs["n"]

    def median(name):
        values = runs[name]
        return float(np.median(values)) if np.isfinite(values).any() else math.nan

    return {
        "method": method, "integrand": case.problem.name, "kind": case.kind, "d": case.problem.d,
        "n": case.n, "evaluations": float(np.median(n)), "seeds": int(z.size),
        "exact": case.problem.exact,
        "coverage_1sigma": cov1, "coverage_2sigma": cov2,
        "mean_abs_z": float(np.mean(absz)), "median_abs_z": float(np.median(absz)),
        "flagged": flagged,
        # Runs the error bar missed at 2 sigma without a flag: the silent failures.
        "missed_unflagged": float(np.mean((absz > 2) & (runs["flagged"] == 0))),
        "passes": bool(in_band or flagged > FLAGGED_MAJORITY),
        "calibration": {str(level): float(np.mean(absz <= _normal_quantile(level)))
                        for level in LEVELS},
        "rms_relative_error": float(np.sqrt(np.mean((runs["mean"] / case.problem.exact - 1) ** 2))),
        "median_ess_share": median("ess") / float(np.median(n)),
        "median_pareto_k": median("pareto_k"),
        "median_nonzero_share": median("n_nonzero") / float(np.median(n)),
        # How often each of the diagnostics' main reasons holds (thresholds as documented in
        # `jaxmc.stats.unreliable`), and how often the error bar was exactly zero.
        "share_pareto_k_over_0.7": float(np.mean(runs["pareto_k"] > 0.7)),
        "share_ess_under_20": float(np.mean(runs["ess"] < 20)),
        "share_nonzero_under_10": float(np.mean(runs["n_nonzero"] < 10)),
        "share_q_under_1e-3": float(np.mean(runs["q"] < 1e-3)),
        "share_zero_stderr": float(np.mean(runs["stderr"] == 0)),
    }


# ----------------------------------------------------------------------------
# Reports: the markdown tables and the calibration figure.


def _fmt_share(value: float) -> str:
    return f"{100 * value:.0f}%"


def _cell_list(records: list[dict]) -> str:
    return "; ".join(
        f"{r['method']} on {r['integrand']} (cov 2σ {r['coverage_2sigma']:.2f}, flagged "
        f"{_fmt_share(r['flagged'])}, missed at 2σ unflagged {_fmt_share(r['missed_unflagged'])}, "
        f"median k̂ {r['median_pareto_k']:.2f})"
        for r in records
    )


def _matrix(records: list[dict], methods: list[str]) -> str:
    """Integrands by methods: '2σ coverage / flagged share', a ✗ on cells that fail the rule."""
    by_cell = {(r["integrand"], r["method"]): r for r in records}
    rows = []
    for name in dict.fromkeys(r["integrand"] for r in records):
        row = [name]
        for m in methods:
            r = by_cell.get((name, m))
            if r is None:
                row.append("-")
                continue
            mark = "" if r["passes"] else " ✗"
            row.append(f"{r['coverage_2sigma']:.2f} / {_fmt_share(r['flagged'])}{mark}")
        rows.append(row)
    return markdown_table(["integrand", *methods], rows)


def _table(records: list[dict]) -> str:
    header = ["method", "integrand", "kind", "d", "n", "seeds", "cov 1σ", "cov 2σ", "mean |z|",
              "flagged", "missed unflagged", "median k̂", "median ess/n", "s", "passes"]
    rows = [
        [r["method"], r["integrand"], r["kind"], r["d"], r["n"], r["seeds"],
         r["coverage_1sigma"], r["coverage_2sigma"], r["mean_abs_z"], _fmt_share(r["flagged"]),
         _fmt_share(r["missed_unflagged"]), r["median_pareto_k"], r["median_ess_share"], r["seconds"], "yes" if r["passes"] else "**no**"]
        for r in records
    ]
    return markdown_table(header, rows)


def _plot(ctx: Context, records: list[dict], methods: list[str], name: str) -> str | None:
    plt = pyplot(ctx)
    if plt is None:
        return None
    from matplotlib.colors import BoundaryNorm, ListedColormap

    integrands = list(dict.fromkeys(r["integrand"] for r in records))
    by_cell = {(r["integrand"], r["method"]): r for r in records}
    panels = len(methods)
    cols = min(5, panels)
    panel_rows = -(-panels // cols)
    heat_height = 0.5 * len(integrands) + 1.8
    fig = plt.figure(figsize=(3.3 * cols + 3.5, heat_height + 3.0 * panel_rows + 0.6),
                     layout="constrained")
    top, bottom = fig.subfigures(2, 1, height_ratios=[heat_height, 3.0 * panel_rows + 0.6])

    # Top: the cells coloured by 2-sigma coverage, annotated with the flagged share.
    ax = top.subplots()
    bounds = [0.0, 0.5, 0.8, 0.9, 0.99, 1.0001]
    cmap = ListedColormap(["#8b0000", "#e34a33", "#fdbb84", "#a1d99b", "#9ecae1"])
    cov = np.array([[by_cell[(i, m)]["coverage_2sigma"] if (i, m) in by_cell else np.nan
                     for m in methods] for i in integrands])
    image = ax.imshow(cov, cmap=cmap, norm=BoundaryNorm(bounds, cmap.N), aspect="auto")
    for (row, col), value in np.ndenumerate(cov):
        r = by_cell.get((integrands[row], methods[col]))
        if r is None:
            continue
        ax.text(col, row, f"{value:.2f}\nflag {_fmt_share(r['flagged'])}", ha="center",
                va="center", fontsize=7, color="w" if value < bounds[1] else "k")
        if r["flagged"] > FLAGGED_MAJORITY:  # announced as untrustworthy
            ax.add_patch(plt.Rectangle((col - 0.5, row - 0.5), 1, 1, fill=False, lw=0,
                                       hatch="//", edgecolor="0.45"))
        if not r["passes"]:
            ax.add_patch(plt.Rectangle((col - 0.48, row - 0.48), 0.96, 0.96, fill=False, lw=2.5,
                                       edgecolor="k"))
    ax.set_xticks(range(len(methods)), methods, rotation=20, ha="right", fontsize=8)
    ax.set_yticks(range(len(integrands)), integrands, fontsize=8)
    ax.set_title("2σ coverage (share of seeds with |mean − I| ≤ 2 stderr; nominal 0.954) and share "
                 "of runs flagged unreliable\nhatched: flagged in most runs; black frame: fails "
                 "the rule (coverage outside [0.9, 0.99] and not flagged in most runs)", fontsize=9)
    top.colorbar(image, ax=ax, ticks=bounds[:-1] + [1.0], fraction=0.025, pad=0.01)

    # Below: one calibration panel per method, empirical against nominal coverage.
    colours = plt.get_cmap("tab20")(np.linspace(0, 1, max(len(integrands), 2)))
    levels = np.array(LEVELS)
    seeds = max(r["seeds"] for r in records)
    band = 2 * np.sqrt(levels * (1 - levels) / seeds)
    axes = np.atleast_1d(bottom.subplots(panel_rows, cols, squeeze=False)).ravel()
    for ax in axes[panels:]:
        ax.set_visible(False)
    for k, m in enumerate(methods):
        ax = axes[k]
        ax.fill_between(levels, levels - band, levels + band, color="0.85", lw=0)
        ax.plot([0.45, 1], [0.45, 1], color="k", lw=0.8)
        for i, integrand in enumerate(integrands):
            r = by_cell.get((integrand, m))
            if r is not None:
                ys = [r["calibration"][str(level)] for level in LEVELS]
                ax.plot(levels, ys, marker="o", ms=2.5, lw=1, color=colours[i],
                        ls="-" if r["passes"] else "--", label=integrand)
        ax.set_xlim(0.45, 1.0)
        ax.set_ylim(0.0, 1.02)
        ax.set_title(m, fontsize=9)
        ax.tick_params(labelsize=7)
        if k % cols == 0:
            ax.set_ylabel("empirical coverage", fontsize=8)
        if k // cols == panel_rows - 1:
            ax.set_xlabel("nominal coverage", fontsize=8)
    handles, labels = axes[0].get_legend_handles_labels()
    bottom.legend(handles, labels, loc="outside right center", fontsize=7, frameon=False)
    bottom.suptitle(
        "Calibration per method: share of seeds with |mean − I| ≤ z·stderr against the normal "
        f"coverage of z (grey: ±2 binomial sd at {seeds} seeds; dashed: the cell fails the rule)",
        fontsize=9,
    )
    fig.savefig(ctx.out / name, dpi=100)
    plt.close(fig)
    return name


# ----------------------------------------------------------------------------


def _mean_flagged(records: list[dict]) -> float:
    """The share of runs flagged over `records` (cells of equal seeds); NaN for none."""
    return float(np.mean([r["flagged"] for r in records])) if records else math.nan


def run(ctx: Context) -> Result:
    with jax.enable_x64(True):
        return measure(ctx, cases(), list(METHODS), SEEDS)


def measure(ctx: Context, chosen: list[Case], methods: list[str], seeds: int) -> Result:
    """The suite on the given cases and methods: tables, JSON and the calibration figure."""
    records = []
    start = time.perf_counter()
    for case in chosen:
        for method in methods:
            begin = time.perf_counter()
            runs, setup = run_cell(method, case, seeds)
            record = summarise(method, case, runs)
            record["seconds"] = time.perf_counter() - begin
            record["setup_warnings"] = setup
            for message in setup:
                ctx.log(f"{case.problem.name} / {method}, setting up: {message}")
            records.append(record)
            ctx.log(
                f"{case.problem.name} / {method}: cov2 {record['coverage_2sigma']:.3f}, flagged "
                f"{_fmt_share(record['flagged'])}, {record['seconds']:.1f} s "
                f"({time.perf_counter() - start:.0f} s)"
            )
    failing = [r for r in records if not r["passes"]]
    # Calibrated error bars that were flagged anyway: false alarms, by the coverage's measure.
    over_flagged = [
        r for r in records
        if PASS_BAND[0] <= r["coverage_2sigma"] <= PASS_BAND[1] and r["flagged"] > FLAGGED_MAJORITY
    ]
    # The false-alarm rate: the share of runs flagged where the error bar was calibrated.
    calibrated = [r for r in records if PASS_BAND[0] <= r["coverage_2sigma"] <= PASS_BAND[1]]
    false_alarms = {m: _mean_flagged([r for r in calibrated if r["method"] == m]) for m in methods}
    false_alarms["all"] = _mean_flagged(calibrated)
    setups = [f"{r['method']} on {r['integrand']}: {m}" for r in records for m in r["setup_warnings"]]
    notes = (
        f"{seeds} seeds per cell, float64; n evaluations per run (`stratified`: the largest "
        "cubic grid of two-point cells within n; `integrate adaptive`: whole rounds; `importance`: "
        "a `Grid` adapted once per integrand by `fit.adapt` with key 1 on the same budget, then "
        "fixed). `cov 1σ`/`cov 2σ`: share of seeds with |mean − I| ≤ 1/2 stderr, read with "
        "Student's t where the error bar has few degrees of freedom (`Estimate.dof`: |z| "
        "mapped to the normal |z| of the same tail) (nominal 0.683/0.954); `mean |z|` "
        "(nominal 0.80; inf when "
        "some run reported a zero error bar while wrong); `flagged`: share of runs "
        "`jaxmc.stats.unreliable` flags; `missed unflagged`: share of runs outside 2σ and "
        "not flagged (the silent failures); `median k̂`, `median ess/n`: the diagnostics' medians; "
        "`s`: wall time of the cell (compilation included). A cell passes when cov 2σ ∈ "
        f"[{PASS_BAND[0]}, {PASS_BAND[1]}] or more than half its runs are flagged. With {seeds} "
        f"seeds a coverage of 0.954 is measured to ±{math.sqrt(0.954 * 0.046 / seeds):.3f} (1 sd)."
    )
    verdict = (
        f"{len(records) - len(failing)} of {len(records)} cells pass"
        + (": every cell's error bar is right or flagged." if not failing else
           "; failing: " + _cell_list(failing) + ".")
        + f"\n\nFalse alarms (runs flagged in the {len(calibrated)} calibrated cells): "
        + f"{100 * false_alarms['all']:.1f}% overall; "
        + ", ".join(f"{m} {100 * v:.1f}%" for m, v in false_alarms.items()
                    if m != "all" and not math.isnan(v)) + "."
        + f"\n\nCalibrated (cov 2σ in [{PASS_BAND[0]}, {PASS_BAND[1]}]) yet flagged in most runs: "
        + (_cell_list(over_flagged) if over_flagged else "none") + "."
        + ("\n\nWarnings while setting methods up (not from the measured runs):\n\n"
           + "\n".join(f"- {line}" for line in setups) if setups else "")
    )
    suffix = "-quick" if ctx.quick else ""
    plot = _plot(ctx, records, methods, f"coverage{suffix}.png")
    markdown = "\n\n".join([
        notes, "2σ coverage / flagged share (✗: fails the rule):", _matrix(records, methods),
        verdict, "All cells:", _table(records),
    ])
    data = {
        "seeds": seeds, "n": N, "levels": list(LEVELS), "pass_band": list(PASS_BAND),
        "flagged_majority": FLAGGED_MAJORITY, "methods": methods,
        "failing": [[r["method"], r["integrand"]] for r in failing],
        "over_flagged": [[r["method"], r["integrand"]] for r in over_flagged],
        "false_alarms": false_alarms, "cells": records,
    }
    return Result(markdown=markdown, data=data, plots=[plot] if plot else [])
