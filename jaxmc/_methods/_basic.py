r"""The methods that train nothing: plain Monte Carlo, jittered strata, randomised QMC."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx

from .._stream._sizes import QMC_MIN_REPLICAS
from ._method import AbstractMethod, Problem, Run


class Plain(AbstractMethod):
    r"""Plain Monte Carlo: i.i.d. uniform points in the box, $\hat I = \frac{V}{n}\sum_i f(x_i)$
    and its variance $s^2/n$ (Owen, *Monte Carlo theory, methods and examples*, ch. 2;
    PBRT 3rd ed. §13.2)."""

    name: ClassVar[str] = "plain"

    def run(self, key, problem: Problem, budget: int) -> Run:
        return Run(problem.stream("plain", key, budget), self)


class Stratified(AbstractMethod):
    r"""Jittered strata: each block of points is one point in each cell of a grid over the box
    (Owen, *Monte Carlo theory, methods and examples*, ch. 8; PBRT 3rd ed. §13.8.1); each block
    is one independent randomisation, and the variance comes from the spread of the
    blocks' means."""

    name: ClassVar[str] = "stratified"

    def run(self, key, problem: Problem, budget: int) -> Run:
        return Run(problem.stream("stratified", key, budget), self)


class QMC(AbstractMethod):
    r"""Randomised quasi-Monte Carlo that keeps its convergence rate.

    $R$ independently scrambled Sobol' sequences (Owen's scrambling with a digital shift),
    each walked block by block as one growing net; the mean is their average and its variance
    $s^2/R$ from their spread, with $R - 1$ degrees of freedom (`Estimate.dof`; its
    `interval` is Student's $t$). On smooth integrands the error falls like $n^{-1}$ or faster
    (plain Monte Carlo: $n^{-1/2}$); it is never much worse than plain Monte Carlo, in any
    dimension (Owen 1997, scrambled net variance).

    **Fields:**

    - `min_replicas`: with a budget `n`, each replica gets the largest power of two of points
      that `min_replicas` replicas fit in, and the rest of the budget buys more replicas
      (3 to 5 by default): at QMC's rates fewer, larger nets are more accurate, and 3 replicas
      leave the error bar 2 degrees of freedom. What whole nets leave buys each replica the
      next points of its sequence, smaller nets that its mean weighs less (a net of half the
      points by a quarter of the weight per point, as a scrambled net's variance on a smooth
      integrand, O(s^-3), asks), so that at least 96% of `n` is spent and
      each replica's mean stays unbiased. With a tolerance there are 8 replicas and the
      tolerance is checked when each holds a power of two of points, from $2^{10}$ on, and
      must pass twice in a row.
    """

    min_replicas: int = eqx.field(default=QMC_MIN_REPLICAS, static=True)
    name: ClassVar[str] = "qmc"

    def __check_init__(self):
        if not isinstance(self.min_replicas, int) or self.min_replicas < 2:
            raise ValueError(f"QMC needs `min_replicas` >= 2 (a spread), got {self.min_replicas!r}.")

    def run(self, key, problem: Problem, budget: int) -> Run:
        return Run(problem.stream("qmc", key, budget, min_replicas=self.min_replicas), self)
