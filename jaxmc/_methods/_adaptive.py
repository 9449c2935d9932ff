r"""`Adaptive`: a VEGAS+ grid trained, refined as it is used, then streamed."""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import ClassVar, NamedTuple

import jax
import jax.numpy as jnp

from .._checks import is_concrete
from .._fit._vegas import VegasPlusState
from .._stats import Estimate
from .._stream._rounds import (
    FINE_GRID_MAX_DIM,
    MIN_STREAM_BLOCKS,
    adaptive_block,
    fine_grid_bins,
    fixed_for_derivatives,
    frozen_vegas_plus,
    grid_bins,
    refine,
    refine_finer,
    refining_rounds,
    start,
    tail_refining,
    training_rounds,
    uniform_grid,
    vegas_rounds,
)
from .._stream._sizes import ADAPTIVE_PROBE_REACH
from ..fit import Samples, VegasPlus
from ._method import AbstractMethod, Problem, Run, stage, switch, when
from ._one_of import OneOf


class Adaptive(AbstractMethod):
    r"""VEGAS+ (Lepage 2021): a separable grid map with adaptive stratification of its unit cube.

    Three stages of VEGAS+ rounds (`jaxmc.fit.VegasPlus`) of one size, about budget/40
    points (a power of two from 256 to $2^{14}$), on a grid of 64 to 256 bins per axis:

    1. **Training**: up to ten rounds on at most a quarter of the budget adapt a uniform
       grid; their estimates are discarded.
    2. **Refining**: the rest of a fixed budget (with a tolerance, up to 32 rounds) goes
       to rounds that each estimate the integral and go on refining the grid and the
       allocation, as vegas adapts through the iterations it reports. Their estimates are
       averaged with weights growing with the round, fixed in advance, so the average stays
       unbiased; the error bar is their scatter.
    3. **Streaming**, with a tolerance the refining rounds did not meet: the last grid,
       frozen, streams until the tolerance or the budget (sharded over devices); the
       result is that stream's estimate alone.

    With only a tolerance, the grid first trains as for $2^{17}$ evaluations (rounds of
    $2^{11}$ points, 64 bins per axis), and trains anew for the whole budget where that grid
    needs more than twice $2^{17}$ evaluations for `rtol` (its last round's relative
    variance per evaluation over `rtol` squared): a long run pays for a larger training.

    **Fields:**

    - `state`: a trained VEGAS+ state (`jaxmc.fit.VegasPlus`'s), or `None` to train one.
      Given a state (an earlier result's `plan`), the method skips training and goes on
      refining that state.
    - `finer`: refine on rounds 4x the training's on a grid subdivided to 4x its bins, as
      vegas's many increments do near a singularity (a fixed budget of at least six such
      rounds; may be traced). `Auto` sets it where the integrand's values have a power-law
      tail.
    """

    state: VegasPlusState | None = None
    finer: bool | jax.Array = False
    name: ClassVar[str] = "adaptive"

    @property
    def trained(self) -> bool:
        return self.state is not None

    def run(self, key, problem: Problem, budget: int) -> Run:
        if self.state is not None:
            return Run(self.stream(key, problem, budget), self)
        train_key, anew_key, key = jax.random.split(key, 3)
        sizing = problem.pilot_budget(budget)
        first = train(train_key, problem, sizing)
        probe = dataclasses.replace(self, state=first.state)
        if sizing == budget:
            est = probe.stream(key, problem, budget - first.spent, done=first.spent)
            return Run(dataclasses.replace(est, n=est.n + first.spent), probe,
                       rounds=first.parts)
        # Trained as for `PROBE_BUDGET` (only a tolerance): trained anew for the whole budget
        # where the probe's grid needs more than `PROBE_REACH` times that for the tolerance.
        anew = _needs_more(first.parts, problem.rtol, round_size=first.state.draw.u.shape[0],
                           reach=ADAPTIVE_PROBE_REACH * sizing)
        second = stage(anew, lambda: train(anew_key, problem, budget - first.spent))
        sized = None if second is None else dataclasses.replace(self, state=second.state)
        spent = first.spent + (0 if second is None else second.spent)
        streams = [lambda: probe.stream(key, problem, budget - first.spent, done=first.spent)]
        if sized is not None:
            streams.append(lambda: sized.stream(key, problem, budget - spent, done=spent))
        est = switch(anew, streams)
        est = dataclasses.replace(est, n=est.n + jnp.where(anew, spent, first.spent))
        if is_concrete(anew):
            return (Run(est, sized, rounds=second.parts) if bool(anew)
                    else Run(est, probe, rounds=first.parts))
        # (Traced: the probe's rounds, whose shape the second training's need not share.)
        return Run(est, OneOf(anew.astype(jnp.int32), (probe, sized)), rounds=first.parts)

    def stream(self, key, problem: Problem, budget: int, done=0):
        """Refining rounds from `state` (under `finer`, larger rounds on a finer grid); with a
        tolerance they did not meet, a frozen stream after them."""
        state = fixed_for_derivatives(self.state)
        round_size = state.draw.u.shape[0]
        rounds, size = (0, 0) if problem.tolerant else tail_refining(budget, round_size)
        if not rounds:
            return _refined(key, problem, budget, state, done)

        def finer():
            return refine_finer(key, state, f=problem.f, batched=problem.batched,
                                rounds=rounds, size=size, progress=problem.progress)

        return when(self.finer, finer, lambda: _refined(key, problem, budget, state, done))


class Training(NamedTuple):
    """A VEGAS+ grid's training: its state, the rounds' estimates, the last round's
    `Samples` and the evaluations spent."""

    state: VegasPlusState
    parts: Estimate
    samples: Samples
    spent: int


def train(key, problem: Problem, sizing: int, fine=False) -> Training:
    """A VEGAS+ grid trained from uniform as `Adaptive` trains it for a budget of `sizing`.

    With `fine` (may be traced), in up to `FINE_GRID_MAX_DIM` dimensions, the grid holds
    `fine_grid_bins` and refines at all of them (else at `grid_bins`, `VegasPlus.coarse`):
    near a singularity or on a narrow peak the finer bins resolve it."""
    block = adaptive_block(sizing)
    rounds = training_rounds(sizing, block)
    if fine is False or problem.d > FINE_GRID_MAX_DIM:
        bins, rule = grid_bins(block), VegasPlus(diagnostics=False)
    else:
        bins = fine_grid_bins(block)
        rule = VegasPlus(diagnostics=False, coarse_bins=grid_bins(block), coarse=~jnp.asarray(fine))
    grid = uniform_grid(problem.lo, problem.hi, bins=bins)
    parts, state, samples = vegas_rounds(rule, key, start(rule, key, grid, block=block), rounds,
                                         f=problem.f, batched=problem.batched)
    return Training(state, parts, samples, rounds * block)


@partial(jax.jit, static_argnames=("round_size", "reach"))
def _needs_more(parts, rtol, *, round_size, reach):
    """Whether the trained grid's last round (`parts`, rounds of `round_size`) saw nothing, or
    asks for more than `reach` evaluations to meet `rtol`: its relative variance per
    evaluation over `rtol` squared (with no `rtol`, only an `atol`: always)."""
    mean, variance = parts.mean[-1], parts.variance[-1]
    tiny = jnp.finfo(mean.dtype).tiny
    relative = jnp.sum(variance / jnp.maximum(mean**2, tiny)) * round_size
    blind = jnp.all(mean == 0)
    return blind | (relative > reach * rtol**2)


def _refined(key, problem: Problem, budget: int, state, done):
    """The refining rounds on rounds of the training's size, and with a tolerance they did
    not meet, a frozen stream of the last grid."""
    block = state.draw.u.shape[0]
    refine_key, key = jax.random.split(key)
    rounds = refining_rounds(budget, block, problem.tolerant)
    refined, state = refine(refine_key, state, problem.rtol, problem.atol, f=problem.f,
                            batched=problem.batched, rounds=rounds, tolerant=problem.tolerant,
                            progress=problem.progress)
    rest = budget - rounds * block
    if not problem.tolerant or rest < MIN_STREAM_BLOCKS * block:
        return refined

    def streamed():
        est = problem.stream("adaptive", key, rest, frozen=frozen_vegas_plus(state, block),
                             done=done + rounds * block, round_size=block)
        return dataclasses.replace(est, n=est.n + refined.n)

    return when(problem.met(refined), lambda: refined, streamed)
