r"""How far a tolerance run's budget will get: a forecast from the error's decrease so far.

A stream's standard error falls like $s(n) \propto n^{-\alpha}$: $\alpha = 1/2$ for
independent blocks (the central limit theorem), up to $3/2$ for randomised nets on a
smooth integrand (Owen 1997), less where the nets meet a discontinuity, and about 0 where
the error has stalled (the arithmetic's or the point set's resolution). Fitted by least
squares to $\log s$ against $\log n$ over the checks so far, the rate forecasts the
evaluations that meet the tolerance $\tau$: $n^* = n\,(s/\tau)^{1/\alpha}$. The forecast
is optimistic on purpose, so that a tolerance is never called unreachable by the noise of
its error bars: it uses the fitted rate plus two of its standard errors (a standard error
of $\nu$ degrees of freedom has $\mathrm{sd}(\log s) \approx 1/\sqrt{2\nu}$), at most the
best the stream can do. Only when even that forecast exceeds the budget does the run say
so, while it goes on.
"""

from __future__ import annotations

import math

import numpy as np

from .._diagnostics import rounding_floor


# The fit needs checks spanning at least this factor in evaluations, and this many of them.
MIN_SPAN = 16.0
MIN_CHECKS = 3


class Forecast:
    """Forecasts of a tolerance run, check by check (host side, outside `jit`).

    `best_rate` is the fastest decrease the stream can show ($1/2$ for independent
    blocks, $3/2$ for randomised nets); `budget` the evaluations it may spend.
    """

    def __init__(self, budget: int, best_rate: float):
        self.budget, self.best_rate = budget, best_rate
        self.checks: list[tuple[float, float, float]] = []  # (log n, log(s / tau), dof)
        self.warned = False
        self.needed: float | None = None  # log of the evaluations forecast at the fitted rate

    def unreachable(self, n, mean, stderr, dof, rtol, atol) -> str | None:
        """After a check at `n` evaluations: a warning's text when even the optimistic
        forecast needs more than the budget (the worst component), else None."""
        mean = np.asarray(mean)
        target = np.maximum(np.asarray(atol, float), np.asarray(rtol, float) * np.abs(mean))
        excess = np.max(np.asarray(stderr, float) / np.where(target > 0, target, np.nan))
        # (Below the rounding floor the stream stops there, and says so itself.)
        floored = np.any(target < rounding_floor(mean.dtype) * np.abs(mean))
        if not np.isfinite(excess) or excess <= 1 or int(n) <= 0 or floored:
            self.checks.clear()  # (met, or nothing to forecast: start afresh)
            self.needed = None
            return None
        self.checks.append((math.log(int(n)), math.log(excess), float(np.min(dof))))
        logn, logx, dofs = map(np.asarray, zip(*self.checks))
        recent = logn >= logn[-1] - math.log(MIN_SPAN) - 1e-9
        if len(self.checks) < MIN_CHECKS or logn[-1] - logn[0] < math.log(MIN_SPAN):
            return None
        # The fit over the last MIN_SPAN-fold stretch of checks (and one before it).
        first = max(0, int(np.argmax(recent)) - 1)
        x, y = logn[first:], logx[first:]
        spread = np.sum((x - x.mean()) ** 2)
        rate = -np.sum((x - x.mean()) * (y - y.mean())) / spread
        noise = 1 / math.sqrt(2 * max(np.min(dofs[first:]), 1.0))
        optimistic = min(max(rate, 0.0) + 2 * noise / math.sqrt(spread), self.best_rate)
        fitted = min(rate, self.best_rate)
        self.needed = logn[-1] + logx[-1] / fitted if fitted > 0 else math.inf
        needed = logn[-1] + logx[-1] / optimistic
        if needed <= math.log(self.budget):
            return None
        reach = math.exp(logx[-1] - min(max(rate, 0.0), self.best_rate)
                         * (math.log(self.budget) - logn[-1]))
        return (
            f"integrate: the tolerance looks out of reach: after {int(n):,} evaluations the "
            f"standard error is {math.exp(logx[-1]):.3g} times the tolerance and falls like "
            f"n^-{max(rate, 0.0):.2f}; even at n^-{optimistic:.2f} it needs about "
            f"{_evaluations(needed)} evaluations, more than the budget of {self.budget:,}, "
            f"which should reach about {reach:.3g} times the tolerance. The run goes on; "
            "relax `rtol`/`atol`, raise `max_n`, or give a budget `n`."
        )


def _evaluations(log_n: float) -> str:
    return f"{math.exp(log_n):.2g}" if log_n < 700 else "infinitely many"


def forecast_note(forecast: Forecast) -> str:
    """The forecast for a progress bar: `(needs ~3.2e+07)`, or nothing before a fit."""
    if forecast.needed is None:
        return ""
    return f"(needs ~{_evaluations(forecast.needed)})"
