r"""`Auto`: a pilot races the candidate methods, the winner streams the rest of the budget."""

from __future__ import annotations

import dataclasses
import math
from functools import partial
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import is_concrete
from .._methods._adaptive import Adaptive, train
from .._methods._basic import QMC
from .._methods._grid_qmc import GridQMC
from .._methods._importance import Importance, adapted
from .._methods._method import AbstractMethod, Problem, Run, latest, stage, switch
from .._methods._one_of import OneOf
from .._stream._rounds import FINE_GRID_MAX_DIM, adaptive_block, training_rounds
from .._stream._sizes import final_net
from ._figures import Figure, unmeasured
from ._grid import adaptive_figure, grid_qmc_figure, grid_qmc_values
from ._mixture import mixture_outlook, mixture_pilot, search_modes
from ._modes import search_evaluations
from ._nets import MAX_NET_GROWTH, REPLICAS, NetFigures, net_values, nets_figures
from ._pilot import Pilot
from ._race import CANDIDATES, choose, grid_can_win, mixture_can_win, pooled_any


class Auto(AbstractMethod):
    r"""A pilot races the candidate methods on a share of the budget; the winner streams
    the rest.

    The candidates are `QMC`, `Adaptive` (the VEGAS+ grid), `GridQMC` (QMC through the
    trained grid's map) and `Importance` from a mixture of Gaussians seeded from the grid.
    Each one's pilot measures its relative variance per evaluation $v$ with an uncertainty;
    the figure of merit is $c\,v$, $c$ its time per evaluation (`costs`). The pilot runs in
    stages, each run only if one of its candidates can still win (`jaxmc`'s `_race`):

    1. QMC on the first quarter of `REPLICAS` scrambled Sobol' nets (the *early look*):
       QMC's figure, plain Monte Carlo's on the same points, and the outlook of a product
       density fitted to half of them and read on the other half (what the grid could do);
    2. the rest of the nets, the same figures on four times the points;
    3. the grid: VEGAS+ trained as `Adaptive` trains it (at most a quarter of the budget),
       its last rounds' figure, and QMC's nets through its map;
    4. the mixture, seeded from the grid's points, given a Gaussian at each mode the grid
       missed (an ascent of $\log|f|$ from QMC's best points, where JAX can differentiate
       $f$), measured on points of its own.

    The stages' sizes are fixed in advance, so a stage that does not run is skipped at run
    time, by a Python branch eagerly and by `lax.cond` under `jit`: the same key gives the
    same estimate both ways. The pilot's evaluations count in the result's `n` but not in
    its mean: the winner streams with fresh randomness, so the estimate stays unbiased.

    **Fields:**

    - `costs`: time per evaluation of QMC, the grid, QMC through the grid and the mixture,
      relative to a Sobol' point, as their streams take on a cheap integrand on a CPU. For an
      integrand that costs more than their maps and draws, set them nearer 1.
    - `confidence`: the standard deviations of its log at which a figure's bounds are read:
      a stage is skipped only when its candidates' optimistic bounds lose to the leader's
      pessimistic one.
    - `pilot_share`: the share of the budget for QMC's pilot nets (their size a power of two,
      64 to 4096 points each).
    - `mixture_points`: the points the mixture's pilot draws, at most.
    - `min_budget`: below it there is no pilot: QMC alone.

    With only a tolerance (`rtol`/`atol`, no `n`), the pilot is sized as for $2^{17}$
    evaluations and the winner streams until the tolerance or `max_n`.
    """

    costs: tuple[float, float, float, float] = eqx.field(default=(1.0, 5.0, 3.0, 15.0),
                                                         static=True)
    confidence: float = eqx.field(default=2.0, static=True)
    pilot_share: float = eqx.field(default=1 / 16, static=True)
    mixture_points: int = eqx.field(default=4096, static=True)
    min_budget: int = eqx.field(default=1 << 14, static=True)
    name: ClassVar[str] = "auto"

    def __check_init__(self):
        if len(self.costs) != len(CANDIDATES) or min(self.costs) <= 0:
            raise ValueError(f"`costs` must be {len(CANDIDATES)} positive numbers, one per "
                             f"candidate {CANDIDATES}, got {self.costs!r}.")
        if not 0 < self.pilot_share <= 0.25:
            raise ValueError(f"`pilot_share` must be in (0, 1/4], got {self.pilot_share!r}.")
        if self.confidence < 0:
            raise ValueError(f"`confidence` must be >= 0, got {self.confidence!r}.")

    def run(self, key, problem: Problem, budget: int) -> Run:
        sizing = problem.pilot_budget(budget)
        if sizing < self.min_budget:
            if budget < 2 * REPLICAS:
                name = "max_n" if problem.probe else "n"
                raise ValueError(f"`{name}` must be >= {2 * REPLICAS} for method 'auto' "
                                 f"(below {self.min_budget} it runs QMC alone), got {budget}.")
            return QMC().run(key, problem, budget)
        return _race(self, key, problem, budget, sizing)


@dataclasses.dataclass(frozen=True)
class Schedule:
    """The pilot's static sizes: points per replica of QMC's nets (the early look on a quarter
    of them), the grid's rounds, the mixture's and the mode search's points, the stream's
    budget after each stage."""

    per_replica: int
    round_size: int
    rounds: int
    mixture_n: int
    search_n: int
    rests: tuple[int, int, int]  # the stream's budget after the early look, the nets, the rest
    sized_rest: int  # what the pilot's sizing budget leaves after every stage

    @property
    def early(self) -> int:
        return self.per_replica // 4

    @property
    def stages(self) -> tuple[int, int, int, int]:
        """Evaluations of each stage (the grid's with the search for modes)."""
        qmc = REPLICAS * self.per_replica
        return (REPLICAS * self.early, qmc - REPLICAS * self.early,
                self.rounds * self.round_size + qmc + self.search_n, self.mixture_n)

    def growth(self, per_replica: int, rest: int) -> float:
        """How much larger the stream's nets on `rest` are than the pilot's (capped)."""
        return min(final_net(rest) / per_replica, MAX_NET_GROWTH)


def schedule(auto: Auto, sizing: int, budget: int, d: int) -> Schedule:
    """The pilot's sizes for a budget of `sizing` (the stream's from `budget`)."""
    share = max(sizing * auto.pilot_share / REPLICAS, 1)
    per_replica = min(max(1 << int(math.floor(math.log2(share))), 64), 4096)
    round_size = adaptive_block(sizing)
    rounds = training_rounds(sizing, round_size)
    # In one dimension a grid is any piecewise-constant density: a mixture adds nothing.
    mixture_n = 0 if d == 1 else min(round_size, auto.mixture_points)
    search_n = search_evaluations(d) if mixture_n else 0  # (the modes are the mixture's)
    s = Schedule(per_replica, round_size, rounds, mixture_n, search_n, (0, 0, 0), 0)
    spent = np.cumsum(s.stages)
    rests = (budget - int(spent[0]), budget - int(spent[1]), budget - int(spent[3]))
    return dataclasses.replace(s, rests=rests, sized_rest=sizing - int(spent[3]))


@jax.jit
def _split(key):
    return tuple(jax.random.split(key, 5))


class _Look(eqx.Module):
    nets: NetFigures
    qmc_after_grid: Figure  # QMC's figure projected to the stream after every stage
    go_on: jax.Array  # whether the grid's stage is worth running


@partial(jax.jit, static_argnames=("z", "costs"))
def _look(y, bins, growths, price, *, z, costs):
    """QMC's pilot nets measured (projected `growths`-fold: to the stream after this stage and
    after the grid's), and whether the grid's stage, at `price`, is worth running."""
    both = nets_figures(y, bins, growths)
    nets, after = (eqx.tree_at(lambda n: n.qmc, both, jax.tree.map(lambda a: a[k], both.qmc))
                   for k in (0, 1))
    go_on = grid_can_win(nets, np.asarray(costs, y.dtype), price, z)
    return _Look(nets, after.qmc, pooled_any(go_on))


@jax.jit
def _joined(early, rest):
    return tuple(jnp.concatenate(parts, axis=1) for parts in zip(early, rest))


class _GridStage(eqx.Module):
    state: Any
    parts: Any  # the training rounds' estimates
    samples: Any
    adaptive: Figure
    through: Figure
    seeded: Any  # the mixture seeded from the grid (None in one dimension)
    seeded_outlook: jax.Array
    modes: Any  # the modes near QMC's best points (None: not searched)
    misses: jax.Array  # the grid misses one of them


class _MixtureStage(eqx.Module):
    figure: Figure
    mixture: Any
    draws: Any


@partial(jax.jit, static_argnames="costs")
def _verdict(look: _Look, grid_on, grid, mixture_on, mixture, stages, search_n, rests, *, costs):
    """From what ran (`grid`, `mixture`: `None` where they did not run eagerly): `(Pilot, the
    evaluations left for the stream)`. The sizes are arrays: one program serves every
    budget."""
    dtype = look.nets.plain.value.dtype
    figures = [look.nets.qmc]
    if grid is not None:
        # A grid that misses a mode hides mass its figure cannot show: neither it nor QMC
        # through it competes.
        usable = grid_on & ~grid.misses
        figures = [_where(grid_on, look.qmc_after_grid, look.nets.qmc),
                   _where(usable, grid.adaptive, unmeasured(dtype)),
                   _where(usable, grid.through, unmeasured(dtype))]
    if mixture is not None:
        figures.append(_where(mixture_on, mixture.figure, unmeasured(dtype)))
    figures = _stack(figures + [unmeasured(dtype)] * (len(CANDIDATES) - len(figures)))
    costs = np.asarray(costs, dtype)
    winner = choose(figures, costs, (jnp.arange(len(CANDIDATES)) == 0) & look.nets.blind)
    ran = jnp.stack([jnp.asarray(True), look.go_on, jnp.asarray(grid_on),
                     jnp.asarray(mixture_on)])
    evaluations = jnp.sum(jnp.where(ran, stages, 0))
    if grid is not None and grid.modes is None:  # (the search needs f's gradients)
        evaluations -= jnp.where(grid_on, search_n, 0)
    pilot = Pilot(CANDIDATES, figures.value, figures.log_sd, figures.value * costs, winner,
                  ran, evaluations.astype(jnp.int32))
    rest = jnp.where(look.go_on, jnp.where(grid_on, rests[2], rests[1]), rests[0])
    return pilot, rest.astype(jnp.int32)


@partial(jax.jit, static_argnames="costs")
def _mixture_on(look: _Look, grid: _GridStage, *, costs):
    """Whether the mixture's stage is worth running, after the grid's: its outlook could win,
    or the grid misses a mode (the mixture is then the one candidate seeded with it)."""
    dtype = look.nets.plain.value.dtype
    measured = _stack([look.qmc_after_grid, grid.adaptive, grid.through, unmeasured(dtype)])
    costs = np.asarray(costs, dtype)
    return pooled_any(mixture_can_win(grid.seeded_outlook, costs, measured) | grid.misses)


def _race(auto: Auto, key, problem: Problem, budget: int, sizing: int) -> Run:
    f, lo, hi, batched, d = problem.f, problem.lo, problem.hi, problem.batched, problem.d
    s = schedule(auto, sizing, budget, d)
    z, costs = auto.confidence, auto.costs
    stream_key, qmc_key, train_key, grid_key, mixture_key = _split(key)
    log2_early = s.early.bit_length() - 1
    dtype = np.dtype(lo.dtype)
    after_grid = s.growth(s.per_replica, s.rests[2])

    # 1. The early look; 2. the rest of the nets.
    early = net_values(qmc_key, lo, hi, f, batched, 0, 1, log2_early)
    first = _look(*early, np.asarray([s.growth(s.early, s.rests[0]),
                                      s.growth(s.early, s.rests[2])], dtype),
                  np.asarray(s.rests[0] / s.rests[2], dtype), z=z, costs=costs)

    def whole_nets():
        rest = net_values(qmc_key, lo, hi, f, batched, 1, 3, log2_early)
        return _look(*_joined(early, rest), np.asarray([s.growth(s.per_replica, s.rests[1]),
                                                        after_grid], dtype),
                     np.asarray(s.rests[1] / s.rests[2], dtype), z=z, costs=costs)

    look = latest(first.go_on, stage(first.go_on, whole_nets), first)
    grid_on = first.go_on & look.go_on if look is not first else False

    # 3. The grid: trained (finer under a power-law tail), measured, QMC's nets through it.
    def grid_stage():
        training = train(train_key, problem, sizing, fine=look.nets.heavy)
        grid = training.state.grid
        figure = adaptive_figure(training.parts, training.samples, z, round_size=s.round_size)
        y, fx = grid_qmc_values(grid_key, grid, f, batched, s.per_replica.bit_length() - 1)
        through = grid_qmc_figure(y, fx, np.asarray(after_grid, dtype))
        seeded, outlook = None, jnp.full((), jnp.inf, lo.dtype)
        modes, misses = None, jnp.asarray(False)
        if s.mixture_n:
            seeded, outlook = mixture_outlook(grid, training.samples)
            modes, misses = search_modes(qmc_key, early[0], grid, training.samples, f=f,
                                         batched=batched)
        return _GridStage(training.state, training.parts, training.samples, figure, through,
                          seeded, outlook, modes, misses)

    grid = stage(grid_on, grid_stage)

    # 4. The mixture.
    mixture, mixture_on = None, False
    if grid is not None and s.mixture_n:
        mixture_on = grid_on & _mixture_on(look, grid, costs=costs)

        def mixture_stage():
            return _MixtureStage(*mixture_pilot(mixture_key, grid.seeded, grid.samples,
                                                grid.modes, grid.misses, f=f,
                                                size=s.mixture_n, batched=batched))

        mixture = stage(mixture_on, mixture_stage)

    pilot, rest = _verdict(look, grid_on, grid, mixture_on, mixture,
                           np.asarray(s.stages, np.int32), np.int32(s.search_n),
                           np.asarray(s.rests, np.int32), costs=costs)

    # The winner streams what its stage left (QMC: one program for every stage's rest).
    done = int(np.sum(s.stages))
    fitted = None if mixture is None else mixture.mixture
    streams = [lambda: (_qmc_stream(problem, stream_key, rest, s.rests, done), fitted)]
    if grid is not None:
        finer = look.nets.heavy & (d <= FINE_GRID_MAX_DIM)
        adaptive, through = Adaptive(grid.state, finer), GridQMC(grid.state.grid)
        streams += [lambda: (adaptive.stream(stream_key, problem, s.rests[2], done), fitted),
                    lambda: (through.stream(stream_key, problem, s.rests[2], done), fitted)]
    if mixture is not None:
        streams.append(lambda: _mixture_stream(problem, stream_key, s, mixture, done))
    est, fitted = switch(pilot.choice, streams)
    est = dataclasses.replace(est, n=est.n + pilot.evaluations)
    options = [QMC(), *([] if grid is None else [adaptive, through]),
               *([] if mixture is None else [Importance(fitted)])]
    rounds = None if grid is None else grid.parts  # (read where `pilot.stages` says it ran)
    if is_concrete(pilot.choice):
        return Run(est, options[int(pilot.choice)], pilot, rounds)
    return Run(est, OneOf(pilot.choice, tuple(options)), pilot, rounds)


def _qmc_stream(problem: Problem, key, rest, rests, done):
    """QMC on the `rest` the pilot left (from the smallest to the largest of `rests`); with a
    tolerance, on the smallest (a cap the tolerance may stop well short of)."""
    if problem.tolerant:
        return problem.stream("qmc", key, min(rests), done=done)
    return problem.qmc_stream(key, rest, max(rests), min(rests), done)


def _mixture_stream(problem, key, s: Schedule, mixture: _MixtureStage, done):
    """The mixture refitted to its pilot's points and its own, then streamed."""
    run = adapted(key, problem, s.rests[2], mixture.mixture, mixture.draws, done,
                  sized_by=s.sized_rest)
    return run.estimate, run.plan.proposal


def _where(pred, a: Figure, b: Figure) -> Figure:
    return jax.tree.map(lambda x, y: jnp.where(pred, x, y), a, b)


def _stack(figures: list[Figure]) -> Figure:
    return Figure(jnp.stack([f.value for f in figures]), jnp.stack([f.log_sd for f in figures]))
