"""Convergence of variance reduction on smooth integrands, and efficiency against SciPy.

Integrands on the unit cube with known integrals: Genz's oscillatory and
Gaussian-peak families (d = 2, 4, 8; Genz 1984, difficulty sums 9.0 and 7.25),
Keister's radial integrand (d = 4, 8; Keister 1996, reference value from a
1-D radial quadrature) and SciPy's `qmc_quad` docstring example, the 8-D
standard normal density over [0, 1]^8 (integral (Φ(1) − 1/2)^8).

- **Error versus n**: RMSE over independent randomisations, against the exact
  value, of scrambled Sobol' (one `n`-point rule per randomisation, as
  `randomized_qmc` averages) and plain MC, for n = 2^6 … 2^k. Sobol' rules
  of 2^m points are nested, so the curve uses prefixes of one scrambled
  sequence per randomisation; plain MC prefixes are plain MC samples too. The
  slope is a least-squares fit of log RMSE on log n (target ≤ −0.9 for d ≤ 4
  with Sobol', −0.5 for plain MC).
- **Stratified vs plain** at equal n (`stratified` with 2 points per cell of a
  cubic grid against `uniform`).
- **MIS** on a two-peak 1-D integrand: each strategy alone, `mis` (balance,
  power), `mis_one_sample`, at equal numbers of integrand evaluations.
- **Efficiency against `scipy.integrate.qmc_quad`**: the same integrands,
  budgets (`n_points` per randomisation, 8 randomisations, scrambled Sobol'
  for both), `error² × time` with error² the mean reported variance over
  repetitions (both report s²/8 from the spread of the 8 rules) and the
  fastest steady-state call (jaxmc's compile time reported apart); ratio =
  SciPy's over jaxmc's (> 1: jaxmc ahead).

Everything runs in float64 (`jax.enable_x64`), as SciPy does, so errors down to
1e-12 are resolved.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxmc import points
from jaxmc.estimators import importance, mis, mis_one_sample, randomized_qmc, stratified, uniform

from . import problems
from ._harness import Context, Result, markdown_table, optional_import, time_call
from .problems import Problem


TITLE = "Convergence: randomised QMC, stratification and MIS vs plain MC and scipy.integrate.qmc_quad"


def _problems(quick: bool) -> list[Problem]:
    if quick:  # each problem costs six compiles and 2 × 128 efficiency calls
        return [problems.genz_oscillatory(2), problems.keister(8), problems.scipy_normal(8)]
    return [
        *(problems.genz_oscillatory(d) for d in (2, 4, 8)),
        *(problems.genz_gaussian(d) for d in (2, 4, 8)),
        problems.keister(4),
        problems.keister(8),
        problems.scipy_normal(8),
    ]


def _slope(ns, errors) -> float:
    return float(np.polyfit(np.log(ns), np.log(errors), 1)[0])


def _prefix_rmse(problem: Problem, kind: str, log2_max: int, reps: int, seed: int):
    """RMSE at n = 2^6..2^log2_max from prefixes of one point set per repetition."""
    n_max = 2**log2_max
    ns = 2 ** np.arange(6, log2_max + 1)
    d = problem.d

    def errors(key):
        if kind == "sobol":
            u = points.sobol(n_max, d, key=key)
        else:
            u = jax.random.uniform(key, (n_max, d))
        y = problem.jax_f(u)
        csum = jnp.cumsum(y)
        return csum[ns - 1] / ns - problem.exact

    # Batches of 16 randomisations: vmapped, with bounded memory.
    batched = jax.jit(jax.vmap(errors))
    keys = jax.random.split(jax.random.key(seed), reps).reshape(-1, 16)
    errs = np.concatenate([np.asarray(batched(k)) for k in keys])
    return ns, np.sqrt(np.mean(errs**2, axis=0))


def _rmse_of(fn: Callable, reps: int, seed: int, exact: float) -> float:
    keys = jax.random.split(jax.random.key(seed), reps)
    means = np.asarray(jax.jit(jax.vmap(lambda k: fn(k).mean))(keys))
    return float(np.sqrt(np.mean((means - exact) ** 2)))


class _Normal(eqx.Module):
    mu: jax.Array
    sigma: jax.Array

    def sample(self, key, n):
        x = self.mu + self.sigma * jax.random.normal(key, (n,), dtype=self.mu.dtype)
        return x, self.pdf(x)

    def pdf(self, x):
        return jnp.exp(-0.5 * ((x - self.mu) / self.sigma) ** 2) / (self.sigma * np.sqrt(2 * np.pi))


def _mis_table(reps: int, n: int) -> tuple[list[list], dict]:
    narrow = _Normal(jnp.asarray(-2.0), jnp.asarray(0.35))
    broad = _Normal(jnp.asarray(2.0), jnp.asarray(1.7))

    def f(x):  # a narrow peak at -2 and a broad one at 2; integral 1.5
        return _Normal(jnp.asarray(-2.0), jnp.asarray(0.3)).pdf(x) + 0.5 * _Normal(
            jnp.asarray(2.0), jnp.asarray(1.5)
        ).pdf(x)

    P = [narrow, broad]
    cases = {
        "narrow proposal only": lambda k: importance(k, f, narrow, n),
        "broad proposal only": lambda k: importance(k, f, broad, n),
        "mis balance (n/2 each)": lambda k: mis(k, f, P, (n // 2, n // 2)),
        "mis power β=2": lambda k: mis(k, f, P, (n // 2, n // 2), heuristic="power"),
        "mis_one_sample balance": lambda k: mis_one_sample(k, f, P, jnp.array([0.5, 0.5]), n),
    }
    data = {name: _rmse_of(fn, reps, 100 + i, 1.5) for i, (name, fn) in enumerate(cases.items())}
    rows = [[name, n, rmse] for name, rmse in data.items()]
    return rows, data


def _efficiency(problem: Problem, n: int, reps: int, scipy_integrate, scipy_qmc, seed: int) -> dict:
    """Time (fastest of `timed_calls` calls) and error² (over `reps` calls) of both methods."""
    timed_calls = min(reps, 32)
    lo, hi = jnp.zeros(problem.d), jnp.ones(problem.d)
    one = lambda k: randomized_qmc(k, problem.jax_f, lo, hi, n, replicas=8, batched=True)
    call = jax.jit(one)
    keys = jax.random.split(jax.random.key(seed), reps)
    # The first call compiles; then `timed_calls` calls on new keys (the first key again first).
    calls = iter([keys[0], *keys[:timed_calls]])
    jax_timing = time_call(lambda: call(next(calls)), repeats=timed_calls)
    compile_s = jax_timing.first_s
    # Error² over all `reps` calls (the same estimator, vmapped over batches of keys with
    # about 2^22 points per batch, so memory stays bounded).
    many = jax.jit(jax.vmap(one))
    batch = max(1, min(reps, 2**22 // (8 * n)))
    parts = [many(keys[i : i + batch]) for i in range(0, reps, batch)]
    est = jax.tree.map(lambda *xs: np.concatenate([np.asarray(x) for x in xs]), *parts)
    # The minimum over calls: the machine may be shared, and noise only adds time.
    jax_t, jax_var = jax_timing.min_s, float(np.mean(est.variance))
    out = {"n_points": n, "n_estimates": 8, "calls": reps, "jaxmc_compile_s": compile_s,
           "jaxmc_s": jax_t, "jaxmc_mse": float(np.mean((est.mean - problem.exact) ** 2)),
           "jaxmc_var": jax_var}
    if scipy_integrate is None:
        return out
    # qmc_quad passes x of shape (d, n).
    numpy_f = lambda x: problem.numpy_f(x.T)
    qrngs = iter([scipy_qmc.Sobol(problem.d, rng=np.random.default_rng(seed * 100_000 + r))
                  for r in range(reps)])
    results = []

    def scipy_call():
        results.append(scipy_integrate.qmc_quad(numpy_f, np.zeros(problem.d), np.ones(problem.d),
                                                n_estimates=8, n_points=n, qrng=next(qrngs)))

    scipy_timing = time_call(scipy_call, repeats=reps - 1)
    errs = [float(res.integral) - problem.exact for res in results]
    variances = [float(res.standard_error) ** 2 for res in results]
    # SciPy does not compile: its fastest call may be the first.
    sp_t, sp_var = min(scipy_timing.seconds), float(np.mean(variances))
    out.update(scipy_s=sp_t, scipy_mse=float(np.mean(np.square(errs))), scipy_var=sp_var,
               ratio=(sp_var * sp_t) / (jax_var * jax_t) if jax_var > 0 else math.inf)
    return out


def _plot(ctx: Context, problem: Problem, curves: dict, eff: list[dict], strat: dict) -> str | None:
    plt = optional_import("matplotlib.pyplot")
    if plt is None:
        return None
    fig, ax = plt.subplots(figsize=(5.5, 4))
    for label, (ns, rmse) in curves.items():
        ax.loglog(ns, rmse, "o-", ms=3, label=f"{label} (slope {_slope(ns, rmse):.2f})")
    ns = curves["plain MC"][0]
    r0 = curves["plain MC"][1][0]
    ax.loglog(ns, r0 * (ns / ns[0]) ** -0.5, "k:", lw=0.8, label="$n^{-1/2}$")
    ax.loglog(ns, curves["scrambled Sobol'"][1][0] * (ns / ns[0]) ** -1.0, "k--", lw=0.8,
              label="$n^{-1}$")
    for e in eff:
        # One randomize_qmc call averages 8 rules: RMSE of one rule = sqrt(8 · MSE).
        ax.plot(e["n_points"], math.sqrt(8 * e["jaxmc_mse"]), "s", color="C2", ms=6)
        if "scipy_mse" in e:
            ax.plot(e["n_points"], math.sqrt(8 * e["scipy_mse"]), "x", color="C3", ms=8)
    ax.plot([], [], "s", color="C2", label="randomized_qmc (per rule)")
    ax.plot([], [], "x", color="C3", label="scipy qmc_quad (per rule)")
    ax.plot(strat["n"], strat["stratified_rmse"], "^", color="C4", ms=7, label="stratified")
    ax.set_xlabel("n (integrand evaluations per rule)")
    ax.set_ylabel("RMSE")
    ax.set_title(problem.name)
    ax.legend(fontsize=7)
    fig.tight_layout()
    name = f"convergence_{problem.name}.png"
    fig.savefig(ctx.out / name, dpi=110)
    plt.close(fig)
    return name


def run(ctx: Context) -> Result:
    with jax.enable_x64(True):
        return _run(ctx)


def _run(ctx: Context) -> Result:
    quick = ctx.quick
    log2_max = 14 if quick else 18
    # Scrambled-Sobol' errors are heavy-tailed (LMS + shift): many randomisations are
    # needed for a stable RMSE.
    reps = 64 if quick else 256
    strat_reps = 128 if quick else 512
    eff_budgets = (2**12,) if quick else (2**10, 2**14, 2**16)
    # Scrambled-Sobol' errors are heavy-tailed, so error² needs thousands of rules.
    eff_reps = 128 if quick else 1024
    scipy_integrate = optional_import("scipy.integrate")
    scipy_qmc = optional_import("scipy.stats.qmc") if scipy_integrate is not None else None
    if scipy_integrate is None:
        ctx.log("scipy missing: the qmc_quad comparison is skipped")

    conv_rows, strat_rows, eff_rows, plots = [], [], [], []
    data: dict = {"problems": {}}
    for i, problem in enumerate(_problems(quick)):
        ctx.log(f"{problem.name}: convergence")
        curves = {
            "scrambled Sobol'": _prefix_rmse(problem, "sobol", log2_max, reps, 10 * i),
            "plain MC": _prefix_rmse(problem, "plain", log2_max, reps, 10 * i + 1),
        }
        slopes = {k: _slope(*v) for k, v in curves.items()}
        conv_rows.append([problem.name, problem.d, slopes["scrambled Sobol'"], slopes["plain MC"],
                          curves["scrambled Sobol'"][1][-1], curves["plain MC"][1][-1]])

        m = max(int((2**12 / 2) ** (1 / problem.d)), 2)
        counts = (m,) * problem.d
        n_strat = 2 * m**problem.d
        lo, hi = jnp.zeros(problem.d), jnp.ones(problem.d)
        s_rmse = _rmse_of(lambda k: stratified(k, problem.jax_f, lo, hi, counts, batched=True),
                          strat_reps, 10 * i + 2, problem.exact)
        p_rmse = _rmse_of(lambda k: uniform(k, problem.jax_f, lo, hi, n_strat, batched=True),
                          strat_reps, 10 * i + 3, problem.exact)
        strat = {"n": n_strat, "counts": counts, "stratified_rmse": s_rmse, "plain_rmse": p_rmse}
        strat_rows.append([problem.name, f"{m}^{problem.d} × 2", n_strat, s_rmse, p_rmse,
                           p_rmse / s_rmse])

        ctx.log(f"{problem.name}: efficiency against qmc_quad")
        eff = [_efficiency(problem, n, eff_reps, scipy_integrate, scipy_qmc, 10 * i + 4)
               for n in eff_budgets]
        for e in eff:
            eff_rows.append([problem.name, e["n_points"], math.sqrt(e["jaxmc_mse"]),
                             e.get("scipy_mse", math.nan) ** 0.5, math.sqrt(e["jaxmc_var"]),
                             e.get("scipy_var", math.nan) ** 0.5, e["jaxmc_s"] * 1e3,
                             e.get("scipy_s", math.nan) * 1e3, e["jaxmc_compile_s"],
                             e.get("ratio", math.nan)])
        plot = _plot(ctx, problem, curves, eff, strat)
        if plot:
            plots.append(plot)
        data["problems"][problem.name] = {
            "d": problem.d,
            "exact": problem.exact,
            "curves": {k: {"n": v[0].tolist(), "rmse": v[1].tolist()} for k, v in curves.items()},
            "slopes": slopes,
            "stratified": strat,
            "efficiency": eff,
        }

    ctx.log("MIS on a two-peak integrand")
    mis_rows, mis_data = _mis_table(reps=200 if quick else 1000, n=256)
    data["mis"] = mis_data

    ratios = [row[-1] for row in eff_rows if not math.isnan(row[-1])]
    markdown = "\n\n".join([
        f"RMSE over {reps} randomisations; n = 2^6 … 2^{log2_max}; float64.",
        "### Error-versus-n slopes\n\n" + markdown_table(
            ["integrand", "d", "Sobol' slope", "plain slope", f"Sobol' RMSE @2^{log2_max}",
             f"plain RMSE @2^{log2_max}"], conv_rows),
        "### Stratified vs plain MC at equal n\n\n" + markdown_table(
            ["integrand", "strata × per stratum", "n", "stratified RMSE", "plain RMSE",
             "plain/stratified"], strat_rows),
        "### MIS on a two-peak integrand (RMSE, equal evaluations)\n\n" + markdown_table(
            ["estimator", "n", "RMSE"], mis_rows),
        "### Efficiency against scipy.integrate.qmc_quad\n\n"
        "8 scrambled-Sobol' randomisations of `n_points` each per call, "
        f"{eff_reps} calls per method. error² is the mean reported variance "
        "(s²/8 from the spread of the 8 rules, computed the same way by both and honest by "
        "jaxmc's tests; less noisy than the squared errors, whose root mean is shown as RMSE: "
        "scrambled-Sobol' errors are heavy-tailed); time is the fastest steady-state call "
        "(the minimum is robust to a busy machine). Ratio = "
        "(error² × time) of SciPy over jaxmc (> 1: jaxmc ahead).\n\n" + markdown_table(
            ["integrand", "n_points", "jaxmc RMSE", "scipy RMSE", "jaxmc stderr",
             "scipy stderr", "jaxmc ms", "scipy ms", "jaxmc compile s", "efficiency ratio"],
            eff_rows)
        + (f"\n\nEfficiency ratio: min {min(ratios):.3g}, median {statistics.median(ratios):.3g}."
           if ratios else ""),
    ])
    data["efficiency_ratio_min"] = min(ratios) if ratios else None
    return Result(markdown=markdown, data=data, plots=plots)
