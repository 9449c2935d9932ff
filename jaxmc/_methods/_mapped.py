"""`Mapped`: a method run on a box with infinite limits, through maps of its unbounded axes."""

from __future__ import annotations

import dataclasses

from .._unbounded import AxisMaps, MappedIntegrand
from ._method import AbstractMethod, Problem, Run


class Mapped(AbstractMethod):
    r"""`method` streaming on the finite box that `maps` sends onto an unbounded one: the
    integrand there is $f(x(t))\,|\det x'(t)|$. `jaxmc.integrate` fits the maps to $f$
    when a limit is infinite: per infinite axis,
    $x = c + \tfrac{sk}{2}[(1 - t)^{-1/k} - (1 + t)^{-1/k}]$ on $t \in (-1, 1)$, or
    $x = a \pm sk[(1 - t)^{-1/k} - 1]$ on $t \in (0, 1)$ for a half-line from $a$; the map's
    quartiles (median, on a half-line) are those of $|f|$'s marginal, estimated by two pilots,
    and its tail $k$ the largest that keeps $f\,|x'|$ bounded given the decay of $|f|$
    estimated by probes out to $2^{20}$ scales along each infinite axis and their diagonal
    ($k = 1$ is the rational map $x = c + s\,t/(1 - t^2)$). As a plan it keeps both, so
    that `integrate(..., method=est.plan)` with the same limits reuses the maps too.

    **Fields:** `method` (a method or a plan) and `maps` (the fitted axis maps).
    """

    method: AbstractMethod
    maps: AxisMaps

    @property
    def name(self) -> str:  # type: ignore[override]
        return self.method.name

    @property
    def trained(self) -> bool:
        return True

    def run(self, key, problem: Problem, budget: int) -> Run:
        lo, hi = self.maps.box(problem.lo, problem.hi)
        mapped = dataclasses.replace(
            problem, f=MappedIntegrand(problem.f, self.maps, problem.batched), lo=lo, hi=hi)
        run = self.method.run(key, mapped, budget)
        return run._replace(plan=Mapped(run.plan, self.maps))
