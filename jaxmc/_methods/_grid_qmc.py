r"""`GridQMC`: randomised QMC through a trained VEGAS grid's map."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp

from .._stream._rounds import fixed_for_derivatives
from .._stream._sizes import QMC_MIN_REPLICAS
from ..proposals import Grid
from ._adaptive import train
from ._edged_grid import BENT_REPLICAS, edged
from ._method import AbstractMethod, Problem, Run


class GridQMC(AbstractMethod):
    r"""Scrambled Sobol' nets carried through a trained VEGAS grid's map.

    With $x = G(u)$ the grid's map and $q$ its density, the values $f(G(u))/q(G(u))$ of
    `QMC`'s nets are importance sampling from the grid, with QMC's rate on what is left,
    $f/q$, which is flatter and smoother than $f$ where the grid fits. Where the grid
    follows a singularity on a face of the box (its edges there spaced as a power law), its
    bins there map in that power of the distance to the face, so that $f/q$ stays bounded
    (`EdgedGrid`); QMC through such a map streams at least 8 replicas, whose means are
    skewed there.

    **Fields:**

    - `grid`: a trained `jaxmc.proposals.Grid`, or `None` to train one as `Adaptive` does
      (its training's evaluations count in the budget, not in the estimate).
    """

    grid: Grid | None = None
    name: ClassVar[str] = "grid_qmc"

    @property
    def trained(self) -> bool:
        return self.grid is not None

    def run(self, key, problem: Problem, budget: int) -> Run:
        if self.grid is not None:
            return Run(self.stream(key, problem, budget), self)
        train_key, key = jax.random.split(key)
        training = train(train_key, problem, problem.pilot_budget(budget))
        plan = dataclasses.replace(self, grid=training.state.grid)
        est = plan.stream(key, problem, budget - training.spent, done=training.spent)
        return Run(dataclasses.replace(est, n=est.n + training.spent), plan,
                   rounds=training.parts)

    def stream(self, key, problem: Problem, budget: int, done=0):
        """`budget` evaluations of QMC's nets through the grid (bent at singular faces, with
        at least `BENT_REPLICAS` replicas there): one compiled program either way."""
        bent = edged(fixed_for_derivatives(self.grid))
        if problem.tolerant:  # (8 replicas, nets that grow to the tolerance)
            return problem.stream("qmc", key, budget, frozen=bent, done=done)
        replicas = jnp.where(bent.powered, BENT_REPLICAS, QMC_MIN_REPLICAS)
        return problem.qmc_stream(key, budget, budget, budget, done, frozen=bent,
                                  min_replicas=replicas, most_replicas=BENT_REPLICAS)
