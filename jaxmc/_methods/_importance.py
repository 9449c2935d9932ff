r"""`Importance`: importance sampling from a fixed density, by default a mixture of Gaussians
seeded from a trained VEGAS grid and refitted to its own points."""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Any, ClassVar

import jax

from .._stream._rounds import fixed_for_derivatives
from ._adaptive import train
from ._method import AbstractMethod, Problem, Run
from ._seeded_mixture import adaptation_points, adapted_mixture, mixture_values, seeded_mixture


# Points drawn from the seeded mixture before it is refitted (as `Auto`'s pilot measures it).
SEED_POINTS = 4096


class Importance(AbstractMethod):
    r"""Importance sampling, $\hat I = \frac1n\sum_i f(x_i)/p(x_i)$ with $x_i \sim p$
    (Owen, *Monte Carlo theory, methods and examples*, ch. 9; PBRT 3rd ed. §13.10), streamed in
    blocks of i.i.d. draws.

    **Fields:**

    - `proposal`: the density $p$, any proposal with `sample(key, n)` (a fitted
      `jaxmc.proposals` density, an earlier result's `plan`'s), or `None`: then a VEGAS+
      grid is trained as `Adaptive` trains it, a mixture of 8 diagonal Gaussians is fitted by
      EM to its last round's points weighted by $|f|/q$ (in one dimension: the grid itself,
      any piecewise-constant density) and mixed with the grid at 10%
      (defensive importance sampling, Hesterberg 1995: $f/p \le 10 f/q$ wherever the grid
      bounds $f/q$), and refitted twice to points drawn from itself (population Monte Carlo,
      Cappé et al. 2004), with a wide Gaussian among its parts that bounds the weights where
      the fitted ones fall faster than $f$. The fits' evaluations count in the budget, not in
      the estimate.

    Every sample is treated as an i.i.d. observation (for a mixture whose parts draw fixed
    shares, a conservative error bar: that stratification only lowers the variance).
    """

    proposal: Any = None
    name: ClassVar[str] = "importance"

    @property
    def trained(self) -> bool:
        return self.proposal is not None

    def run(self, key, problem: Problem, budget: int) -> Run:
        if self.proposal is not None:
            return Run(stream(key, problem, budget, self.proposal), self)
        train_key, draw_key, key = jax.random.split(key, 3)
        training = train(train_key, problem, problem.pilot_budget(budget))
        if problem.lo.ndim == 0:  # (in one dimension the grid is any piecewise-constant density)
            plan = Importance(training.state.grid)
            est = stream(key, problem, budget - training.spent, plan.proposal, training.spent)
            return Run(dataclasses.replace(est, n=est.n + training.spent), plan,
                       rounds=training.parts)
        mixture = seeded_mixture(training.state.grid, training.samples)
        size = min(training.samples.weights.shape[0], SEED_POINTS)
        x, p = _draw(draw_key, mixture, size=size)
        draws = (x, mixture_values(x, p, f=problem.f, batched=problem.batched))
        spent = training.spent + size
        run = adapted(key, problem, budget - spent, mixture, draws, spent)
        return run._replace(estimate=dataclasses.replace(run.estimate, n=run.estimate.n + spent),
                            rounds=training.parts)


def adapted(key, problem: Problem, budget: int, mixture, draws, done, sized_by=None) -> Run:
    """Refit `mixture` to its pilot's `draws = (x, f/p)` and to points of its own
    (`adapted_mixture`: as many as a tenth of `sized_by`, by default `budget`, allows; they
    count in `n`, not in the mean), then stream the rest of `budget` from it. `done`:
    evaluations spent before (for the progress bar)."""
    adapt_key, key = jax.random.split(key)
    size = adaptation_points(budget if sized_by is None else sized_by)
    if size:
        mixture = adapted_mixture(adapt_key, mixture, draws, f=problem.f, size=size,
                                  batched=problem.batched)
    est = stream(key, problem, budget - size, mixture, done + size)
    return Run(dataclasses.replace(est, n=est.n + size), Importance(mixture))


def stream(key, problem: Problem, budget: int, proposal, done=0):
    """`budget` evaluations of importance sampling from `proposal` (held fixed for
    derivatives), in the small steps a mixture's arrays need."""
    return problem.stream("importance", key, budget, frozen=fixed_for_derivatives(proposal),
                          done=done, chunk=problem.small_chunk)


@partial(jax.jit, static_argnames="size")
def _draw(key, mixture, *, size):
    return mixture.sample(key, size)
