r"""Infinite limits: `jaxmc.integrate` and `jaxmc.expectation` over unbounded boxes, against
vegas with the tutorial's substitution and SciPy's deterministic cubature.

Each case has a closed form. For each, in float64:

- jaxmc: `integrate(key, f, lo, hi, n=N)` with infinite `lo`/`hi` and its defaults
  (`expectation` for the posterior mean), on `KEYS` keys (`QUICK_KEYS` with `--quick`):
  `relerr`, the RMS of (estimate − I)/I; `ms`, the median wall time of the calls after
  the first (timed apart: `first s`, compilation included); the largest normal-equivalent
  |z| (`normal_equivalent`) and `var ratio`, the empirical variance of the estimates over
  the mean reported variance (1 when the error bars are honest).
- vegas: each infinite axis substituted by hand as in vegas's and Cuba's tutorials,
  $x = a + z/(1 - z)$ on $[a, \infty)$ and $x = z/(1 - z^2)$ on the line, times the
  Jacobian, then the two-step protocol of the `auto` suite (`nitn=10, neval=N/40`
  discarded, then `nitn=10, neval=3N/40`), on `VEGAS_SEEDS` seeds.
- SciPy: `scipy.integrate.cubature` (adaptive Genz-Malik / Gauss-Kronrod cubature, which
  maps infinite limits itself), `quad` for the 1-D case, asked for jaxmc's accuracy:
  `rtol` (`epsrel`) is jaxmc's `relerr` on the case. Deterministic: `relerr` is its one
  error, `ms` the median of `SCIPY_REPEATS` calls.

Efficiency is $1/(\mathrm{relerr}^2 \cdot t)$: for Monte Carlo a property of the method
(error² falls as 1/time). A deterministic rule's error does not trade against time so;
its efficiency is taken at the accuracy asked of it, $1/(\max(\mathrm{relerr},
\mathrm{rtol})^2 \cdot t)$: the time it takes to deliver jaxmc's accuracy. `ratio` is
jaxmc's efficiency over the better of vegas's and SciPy's (> 1: jaxmc ahead), `vs vegas`
over vegas's alone.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import operator
import statistics
import time
import warnings
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

import jaxmc

from ._harness import Context, Result, markdown_table, normal_equivalent, optional_import


TITLE = "Infinite limits: integrate against vegas with substitution and SciPy's cubature"

N = 10**5
KEYS = 32
QUICK_KEYS = 6
VEGAS_SEEDS = 8
VEGAS_NITN = 10
VEGAS_WARMUP_SHARE = 0.25
SCIPY_REPEATS = 3
FLOOR = 1e-15  # (relerr of an exact hit)
INF = math.inf


@dataclasses.dataclass(frozen=True)
class Case:
    """`f(x, xp)` on a batch `(m, d)` of points in the array module `xp`; a posterior case
    gives `(log pi, g)` instead, and `exact` is E[g]."""

    name: str
    f: Callable
    lo: tuple[float, ...]
    hi: tuple[float, ...]
    exact: float
    posterior: bool = False

    @property
    def d(self) -> int:
        return len(self.lo)


_MU = np.array([1.0, -2.0])
_COV = np.array([[1.0, 0.6], [0.6, 2.0]])
_PRECISION = np.linalg.inv(_COV)


def _log_posterior(x, xp):
    r = x - xp.asarray(_MU)
    return -0.5 * xp.sum((r @ xp.asarray(_PRECISION)) * r, axis=1)


def cases() -> list[Case]:
    return [
        Case("Gaussian on R^4", lambda x, xp: xp.exp(-0.5 * xp.sum(x**2, axis=1)),
             (-INF,) * 4, (INF,) * 4, (2 * math.pi) ** 2),
        Case("Student-t kernel nu=3 on R^2",
             lambda x, xp: (1 + xp.sum(x**2, axis=1) / 3) ** -2.5, (-INF,) * 2, (INF,) * 2,
             2 * math.pi),
        Case("Student-t kernel nu=5 on R^2",
             lambda x, xp: (1 + xp.sum(x**2, axis=1) / 5) ** -3.5, (-INF,) * 2, (INF,) * 2,
             2 * math.pi),
        Case("exp(-x) on [0, inf)", lambda x, xp: xp.exp(-x[:, 0]), (0.0,), (INF,), 1.0),
        Case("mixed: [0, inf) x R x [0, 1]",
             lambda x, xp: xp.exp(-x[:, 0] - 0.5 * x[:, 1] ** 2) * (1 + x[:, 2]),
             (0.0, -INF, 0.0), (INF, INF, 1.0), math.sqrt(2 * math.pi) * 1.5),
        Case("posterior mean E[x0] on R^2 (correlated Gaussian)", _log_posterior,
             (-INF,) * 2, (INF,) * 2, float(_MU[0]), posterior=True),
    ]


def _jaxmc(case: Case, n: int, keys: int) -> dict:
    lo, hi = jnp.asarray(case.lo), jnp.asarray(case.hi)
    f = functools.partial(case.f, xp=jnp)  # (one function for every key: compiled once)
    first = operator.itemgetter((slice(None), 0))
    means, errors, seconds, methods = [], [], [], []
    for k in range(keys):
        start = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", jaxmc.ReliabilityWarning)
            if case.posterior:
                est = jaxmc.expectation(jax.random.key(k), first, f, lo, hi, n=n, batched=True)
            else:
                est = jaxmc.integrate(jax.random.key(k), f, lo, hi, n=n, batched=True)
        mean = float(est.mean)
        seconds.append(time.perf_counter() - start)
        means.append(mean)
        errors.append((float(est.stderr), float(est.dof)))
        methods.append(est.method)
    means = np.asarray(means)
    stderr, dof = (np.asarray(v) for v in zip(*errors))
    z = normal_equivalent(np.abs(means - case.exact) / stderr, dof)
    return {
        "relerr": float(np.sqrt(np.mean(((means - case.exact) / case.exact) ** 2))),
        "s": statistics.median(seconds[1:]), "first_s": seconds[0],
        "max_z": float(np.max(z)), "coverage_2sigma": float(np.mean(z <= 2)),
        "var_ratio": float(np.var(means, ddof=1) / np.mean(stderr**2)),
        "methods": {m: methods.count(m) for m in sorted(set(methods))},
    }


def _substituted(case: Case):
    """vegas's integrand on the substituted box: f(x(z)) |x'(z)| (and the box)."""
    lo, hi = np.asarray(case.lo), np.asarray(case.hi)
    two = np.isneginf(lo) & np.isposinf(hi)
    above = np.isposinf(hi) & ~two
    below = np.isneginf(lo) & ~two
    zlo = np.where(two, -1.0, np.where(above | below, 0.0, lo))
    zhi = np.where(two | above | below, 1.0, hi)

    def x_of(z):
        with np.errstate(divide="ignore", invalid="ignore"):
            x = np.where(two, z / (1 - z**2), np.where(above, lo + z / (1 - z),
                                                      np.where(below, hi - z / (1 - z), z)))
            jac = np.where(two, (1 + z**2) / (1 - z**2) ** 2,
                           np.where(above | below, 1 / (1 - z) ** 2, 1.0))
        return x, np.prod(jac, axis=1)

    if case.posterior:
        def fz(z):
            x, jac = x_of(z)
            p = np.exp(case.f(x, np)) * jac
            out = np.stack([p, x[:, 0] * p], axis=1)
            return np.where(np.isfinite(out), out, 0.0)
    else:
        def fz(z):
            x, jac = x_of(z)
            out = case.f(x, np) * jac
            return np.where(np.isfinite(out), out, 0.0)
    return fz, list(zip(zlo, zhi))


def _vegas(case: Case, n: int, seeds: int) -> dict | None:
    vegas, gvar = optional_import("vegas"), optional_import("gvar")
    if vegas is None or gvar is None:
        return None
    fz, bounds = _substituted(case)
    fb = vegas.lbatchintegrand(fz)
    warm = VEGAS_WARMUP_SHARE * n / VEGAS_NITN
    final = (1 - VEGAS_WARMUP_SHARE) * n / VEGAS_NITN
    means, seconds = [], []
    for seed in range(seeds):
        gvar.ranseed(seed)
        start = time.perf_counter()
        integ = vegas.Integrator(bounds)
        integ(fb, nitn=VEGAS_NITN, neval=warm)
        result = integ(fb, nitn=VEGAS_NITN, neval=final)
        value = result[1] / result[0] if case.posterior else result
        seconds.append(time.perf_counter() - start)
        means.append(float(gvar.mean(value)))
    means = np.asarray(means)
    return {"relerr": float(np.sqrt(np.mean(((means - case.exact) / case.exact) ** 2))),
            "s": statistics.median(seconds)}


def _scipy(case: Case, rtol: float) -> dict | None:
    integrate = optional_import("scipy.integrate")
    if integrate is None:
        return None
    if case.posterior:
        def f(x):
            p = np.exp(case.f(x, np))
            return np.stack([p, x[:, 0] * p], axis=-1)
    else:
        def f(x):
            return case.f(x, np)
    seconds, value, how = [], math.nan, ""
    for _ in range(SCIPY_REPEATS):
        start = time.perf_counter()
        if case.d == 1 and not case.posterior:
            value = integrate.quad(lambda t: float(f(np.asarray([[t]]))[0]), case.lo[0],
                                   case.hi[0], epsabs=0.0, epsrel=rtol)[0]
            how = "quad"
        else:
            res = integrate.cubature(f, np.asarray(case.lo), np.asarray(case.hi), rtol=rtol)
            value = res.estimate[1] / res.estimate[0] if case.posterior else float(res.estimate)
            how = f"cubature ({res.status})"
        seconds.append(time.perf_counter() - start)
    return {"relerr": float(abs(value - case.exact) / abs(case.exact)), "rtol": rtol,
            "s": statistics.median(seconds), "how": how}


def _efficiency(result: dict | None) -> float:
    if result is None:
        return math.nan
    return 1.0 / (max(result["relerr"], result.get("rtol", FLOOR)) ** 2 * result["s"])


def run(ctx: Context) -> Result:
    keys = QUICK_KEYS if ctx.quick else KEYS
    n = N // 10 if ctx.quick else N
    with jax.enable_x64(True):
        records = []
        for case in cases():
            mine = _jaxmc(case, n, keys)
            record = {"case": case.name, "n": n, "jaxmc": mine,
                      "vegas": _vegas(case, n, VEGAS_SEEDS // (2 if ctx.quick else 1)),
                      "scipy": _scipy(case, mine["relerr"])}
            effs = {lib: _efficiency(record[lib]) for lib in ("jaxmc", "vegas", "scipy")}
            best = max((e for lib, e in effs.items() if lib != "jaxmc" and not math.isnan(e)),
                       default=math.nan)
            record["efficiency"] = effs
            record["ratio"] = effs["jaxmc"] / best
            record["ratio_vegas"] = effs["jaxmc"] / effs["vegas"]
            records.append(record)
            j = record["jaxmc"]
            ctx.log(f"{case.name}: jaxmc relerr {j['relerr']:.2e} in {j['s'] * 1e3:.0f} ms "
                    f"(first {j['first_s']:.1f} s), max |z| {j['max_z']:.1f}, var ratio "
                    f"{j['var_ratio']:.2f}; ratio {record['ratio']:.3g}")
    header = ["case", "N", "jaxmc relerr", "jaxmc ms", "jaxmc first s", "max abs z",
              "var ratio", "vegas relerr", "vegas ms", "scipy relerr", "scipy ms", "scipy",
              "ratio", "vs vegas", "jaxmc chose"]
    rows = []
    for r in records:
        j, v, s = r["jaxmc"], r["vegas"] or {}, r["scipy"] or {}
        rows.append([r["case"], f"{r['n']:.0e}", j["relerr"], j["s"] * 1e3, j["first_s"],
                     j["max_z"], j["var_ratio"], v.get("relerr", math.nan),
                     v.get("s", math.nan) * 1e3, s.get("relerr", math.nan),
                     s.get("s", math.nan) * 1e3, s.get("how", "-"), r["ratio"], r["ratio_vegas"],
                     ", ".join(f"{m} {c}" for m, c in j["methods"].items())])
    markdown = (
        f"Float64, jaxmc on {keys} keys per case with its defaults; vegas on the substituted "
        f"box ($x = a + z/(1-z)$, $x = z/(1-z^2)$), {VEGAS_SEEDS // (2 if ctx.quick else 1)} "
        "seeds, its tutorial's two-step protocol; SciPy's `cubature` (`quad` in 1-D) asked "
        "for jaxmc's relerr as its `rtol`, its efficiency taken at that accuracy. `max abs z`: the largest normal-equivalent |z| of jaxmc's keys; "
        "`var ratio`: the estimates' variance over the mean reported variance; `ratio`: "
        "jaxmc's efficiency 1/(relerr² · time) over the better of vegas's and SciPy's, `vs "
        "vegas` over vegas's alone.\n\n"
        + markdown_table(header, rows) + "\n"
    )
    return Result(markdown=markdown, data={"cases": records})
