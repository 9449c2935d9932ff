"""`integrate`'s runners: one call's fixed settings, and a method's stream from them."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from .._checks import is_concrete
from .._progress import progress_bar
from ._adaptive import (
    MIN_STREAM_BLOCKS,
    adaptive_block,
    fixed_for_derivatives,
    frozen_vegas_plus,
    grid_bins,
    refine,
    refine_finer,
    refining_rounds,
    tail_refining,
    train_vegas_plus,
    training_rounds,
    uniform_grid,
)
from ._edged_grid import BENT_REPLICAS, edged
from ._pilot_grid import grid_rounds
from ._plan import ADAPTIVE_PROBE_REACH, PROBE_BUDGET, QMC_MIN_REPLICAS, plan
from ._seeded_mixture import adaptation_points, adapted_mixture
from ._stream import stream_on_mesh


class Runner:
    """One call's fixed settings, and a runner per method returning an `Estimate`."""

    def __init__(self, f, lo, hi, chunk, mesh, tolerant, progress, batched, rtol, atol):
        self.f, self.lo, self.hi, self.chunk, self.mesh = f, lo, hi, chunk, mesh
        self.tolerant, self.progress, self.batched = tolerant, progress, batched
        self.rtol, self.atol = rtol, atol
        self.d = 1 if lo.ndim == 0 else lo.shape[0]

    def _stream(self, key, frozen, run_plan, done=0):
        """Stream `run_plan`, `done` evaluations (a pilot's, a training's) already spent."""
        # With a tolerance the run may stop anywhere before its budget (`max_n`, 2^30 by
        # default): the bar counts evaluations, with no total nor time left.
        total = None if self.tolerant else done + run_plan.budget
        with progress_bar(self.progress, total, done):
            return stream_on_mesh(
                key, frozen, self.lo, self.hi, self.rtol, self.atol, f=self.f, plan=run_plan,
                mesh=self.mesh, tolerant=self.tolerant, progress=self.progress,
                batched=self.batched,
            )

    def block_method(self, method, key, budget, done=0, frozen=None, chunk=None,
                     min_replicas=QMC_MIN_REPLICAS):
        run_plan = plan(method, budget, chunk or self.chunk, self.mesh.size, self.d,
                        tolerant=self.tolerant, min_replicas=min_replicas)
        return self._stream(key, frozen, run_plan, done)

    def qmc(self, key, budget, done=0, grid=None, min_replicas=QMC_MIN_REPLICAS):
        """Randomised QMC: scrambled Sobol' nets, carried through a trained `grid`'s map if
        given (importance sampling from it, its density fixed for derivatives)."""
        frozen = None if grid is None else fixed_for_derivatives(grid)
        return self.block_method("qmc", key, budget, done, frozen=frozen,
                                 min_replicas=min_replicas)

    def grid_qmc(self, key, budget, done, grid):
        """`qmc` through a trained `grid`, bent at the faces where it follows a singularity
        (`edged`), with at least `BENT_REPLICAS` replicas there (a branch under `jit`)."""
        bent = edged(grid)

        def through(bent_at_a_face):
            if bent_at_a_face:
                return self.qmc(key, budget, done, grid=bent, min_replicas=BENT_REPLICAS)
            return self.qmc(key, budget, done, grid=grid)

        if is_concrete(bent.powered):
            return through(bool(bent.powered))
        return jax.lax.cond(bent.powered, lambda: through(True), lambda: through(False))

    def mixture(self, key, budget, done, mixture, draws, chunk, sized_by=None):
        """Refit auto's winning `mixture` to its pilot's `draws` and to points of its own
        (`adapted_mixture`: they count in `n`, not in the mean; as many as `sized_by`, by
        default `budget`, allows), then stream from it."""
        adapt_key, key = jax.random.split(key)
        size = adaptation_points(budget if sized_by is None else sized_by)
        if size:
            mixture = adapted_mixture(adapt_key, mixture, draws, f=self.f, size=size,
                                      batched=self.batched)
        mixture = fixed_for_derivatives(mixture)  # (the fits' own derivatives: none)
        est = self.block_method("importance", key, budget - size, done + size, frozen=mixture,
                                chunk=chunk)
        return dataclasses.replace(est, n=est.n + size)

    def adaptive(self, key, budget, probe_rtol=None):
        """Train a VEGAS+ grid from uniform, then refine and stream on it (`_adaptive`).

        The rounds, grid bins and training are sized for `budget`; given `probe_rtol` (a
        tolerance run outside `jit`), first for `PROBE_BUDGET`, and for `budget` anew, with
        fresh keys, only when the probe's trained grid saw nothing or needs more than
        `ADAPTIVE_PROBE_REACH` times that budget for `probe_rtol` (its variance per
        evaluation as auto's pilot measures it, over `probe_rtol`^2). The probe's
        evaluations count in `n`.
        Under `vmap` the probe's sizes stand (its figures are batched).
        """
        spent = 0
        for sizing in ([min(budget, PROBE_BUDGET)] if probe_rtol else []) + [budget]:
            block = adaptive_block(sizing)
            rounds = training_rounds(sizing, block)
            train_key, key = jax.random.split(key)
            grid = uniform_grid(self.lo, self.hi, bins=grid_bins(block))
            if sizing == budget:
                state = train_vegas_plus(train_key, self.f, grid, rounds, block, self.batched)
                break
            variance, blind, _, state, _ = grid_rounds(train_key, grid, jnp.int32(rounds), f=self.f,
                                                    rounds=rounds, round_size=block,
                                                    batched=self.batched)
            if not is_concrete(variance) or (
                not bool(blind) and float(variance) / probe_rtol**2 <= ADAPTIVE_PROBE_REACH * sizing
            ):
                break
            spent += rounds * block
        done = spent + rounds * block
        est = self.trained_grid(key, budget - done, state, block, done)
        return dataclasses.replace(est, n=est.n + done)

    def trained_grid(self, key, budget, state, block, done=0, tail=False):
        """Refining rounds from a trained VEGAS+ `state`; with a tolerance they did not
        meet, a frozen stream after them (`_adaptive`). Under a power-law tail (`tail`, may
        be traced) and a fixed budget, larger rounds on a finer grid (`tail_refining`)."""
        tail_rounds, size = (0, 0) if self.tolerant else tail_refining(budget, block)
        if not tail_rounds or (is_concrete(tail) and not bool(tail)):
            return self._refined_grid(key, budget, state, block, done)

        def finer():
            with progress_bar(self.progress, done + tail_rounds * size, done):
                return refine_finer(key, fixed_for_derivatives(state),
                                    f=self.f, batched=self.batched, rounds=tail_rounds,
                                    size=size, progress=self.progress)

        if is_concrete(tail):
            return finer()
        return jax.lax.cond(tail, finer,
                            lambda: self._refined_grid(key, budget, state, block, done))

    def _refined_grid(self, key, budget, state, block, done):
        """`trained_grid` on rounds of the training's size."""
        refine_key, key = jax.random.split(key)
        rounds = refining_rounds(budget, block, self.tolerant)
        state = fixed_for_derivatives(state)
        with progress_bar(self.progress, done + rounds * block, done):
            refined, state = refine(refine_key, state, self.rtol, self.atol, f=self.f,
                                    batched=self.batched, rounds=rounds, tolerant=self.tolerant,
                                    progress=self.progress)
        rest = budget - rounds * block
        if not self.tolerant or rest < MIN_STREAM_BLOCKS * block:
            return refined

        def streamed():
            run_plan = plan("adaptive", rest, self.chunk, self.mesh.size, self.d, block,
                            tolerant=True)
            est = self._stream(key, frozen_vegas_plus(state, block), run_plan, done + rounds * block)
            return dataclasses.replace(est, n=est.n + refined.n)

        met = jnp.all(refined.stderr <= jnp.maximum(self.atol, self.rtol * jnp.abs(refined.mean)))
        if is_concrete(met):
            return refined if bool(met) else streamed()
        return jax.lax.cond(met, lambda: refined, streamed)
