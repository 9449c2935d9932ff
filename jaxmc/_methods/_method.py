r"""What every method of `integrate` is: an object with options as fields, run on a `Problem`.

A method spends a budget of integrand evaluations on one `Problem` (the integrand, the
box and the call's settings) and returns a `Run`: the `Estimate`, and the *plan*, the
method as it streamed with whatever it trained (a grid, a fitted density), so that
`integrate(..., method=est.plan)` streams at once on another call, without training.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from .._checks import is_concrete
from .._progress import progress_bar
from .._stats import Estimate
from .._stream._engine import stream_on_mesh
from .._stream._sizes import PROBE_BUDGET, QMC_MIN_REPLICAS, dynamic_qmc_sizes, sizes


@dataclasses.dataclass(frozen=True)
class Problem:
    """One `integrate` call: the integrand `f` (bound to its `args`), the box, the
    tolerances (`rtol`, `atol`: arrays, zero when absent) and how to stream (the loop's
    `chunk`, the `mesh` of devices, a progress bar)."""

    f: Callable
    lo: jax.Array
    hi: jax.Array
    batched: bool
    chunk: int
    mesh: Any
    tolerant: bool
    progress: bool
    rtol: Any
    atol: Any
    # A stream from a density that holds `(points, components, d)` arrays runs in smaller
    # steps, which stay in cache.
    small_chunk: int
    # Only a tolerance: pilots and trainings are sized for `PROBE_BUDGET`, not for `max_n`.
    probe: bool = False

    @property
    def d(self) -> int:
        return 1 if self.lo.ndim == 0 else self.lo.shape[0]

    def stream(self, kind: str, key, budget: int, *, frozen=None, done=0, chunk=None,
               min_replicas: int = QMC_MIN_REPLICAS, round_size: int = 0) -> Estimate:
        """`budget` evaluations of the block stream `kind` (`"plain"`, `"stratified"`,
        `"qmc"`, `"importance"` from the density `frozen`, `"adaptive"` VEGAS+ rounds on the
        `frozen` grid and allocation), `done` evaluations already spent (for the progress
        bar)."""
        layout = sizes(kind, budget, chunk or self.chunk, self.mesh.size, self.d, round_size,
                       tolerant=self.tolerant, min_replicas=min_replicas)
        # With a tolerance the run may stop anywhere before its budget: the bar counts
        # evaluations, with no total nor time left.
        total = None if self.tolerant else done + layout.budget
        with progress_bar(self.progress, total, done):
            return stream_on_mesh(
                key, frozen, self.lo, self.hi, self.rtol, self.atol, f=self.f, sizes=layout,
                mesh=self.mesh, tolerant=self.tolerant, progress=self.progress,
                batched=self.batched,
            )

    def qmc_stream(self, key, budget, cap: int, floor: int, done=0, *, frozen=None,
                   min_replicas=QMC_MIN_REPLICAS, most_replicas=QMC_MIN_REPLICAS):
        """Randomised QMC (through the map `frozen`, if given) on `budget` evaluations between
        `floor` and `cap`, in nets that `min_replicas` replicas fit in (at most
        `most_replicas`): both may be traced, one compiled program serves them all
        (`dynamic_qmc_sizes`)."""
        layout = dynamic_qmc_sizes(cap, floor, self.chunk, self.mesh.size, most_replicas)
        with progress_bar(self.progress, None if self.tolerant else done + cap, done):
            return stream_on_mesh(
                key, frozen, self.lo, self.hi, self.rtol, self.atol, budget, min_replicas,
                f=self.f, sizes=layout, mesh=self.mesh, tolerant=False, progress=self.progress,
                batched=self.batched,
            )

    def pilot_budget(self, budget: int) -> int:
        """The budget a pilot or a training is sized for: `budget`, or with only a tolerance
        at most `PROBE_BUDGET` (the run itself may stop long before `max_n`)."""
        return min(budget, PROBE_BUDGET) if self.probe else budget

    def met(self, est: Estimate) -> jax.Array:
        """Whether `est` meets the tolerance (every component)."""
        return jnp.all(est.stderr <= jnp.maximum(self.atol, self.rtol * jnp.abs(est.mean)))


class Run(NamedTuple):
    """What a method's `run` returns: the estimate, the plan that reproduces its stream
    (the method with what it trained), for `Auto` the pilot's record, and where a VEGAS+ grid
    was trained its training rounds (an `Estimate` stacked along its first axis)."""

    estimate: Estimate
    plan: AbstractMethod
    pilot: Any = None
    rounds: Any = None


class AbstractMethod(eqx.Module):
    """A method of `integrate`: options as fields (static), trained state as arrays.

    Subclasses set `name` (what `IntegrationEstimate.method` reports) and implement
    `run(key, problem, budget) -> Run`, spending at most `budget` evaluations.
    """

    name: ClassVar[str]

    def run(self, key: jax.Array, problem: Problem, budget: int) -> Run:
        raise NotImplementedError

    @property
    def trained(self) -> bool:
        """Whether this method holds what it would otherwise train (a plan)."""
        return False


def when(pred, then: Callable, otherwise: Callable, *operands):
    """`then(*operands)` where `pred` holds, else `otherwise(*operands)`: a Python branch
    where `pred` is concrete (only the branch taken is traced and compiled), `lax.cond`
    where it is traced (both compiled, one runs). Both ways run the same computations, so
    eagerly and under `jit` the result is the same."""
    if is_concrete(pred):
        return (then if bool(pred) else otherwise)(*operands)
    return jax.lax.cond(pred, then, otherwise, *operands)


def switch(index, branches, *operands):
    """`branches[index](*operands)`: a Python choice where `index` is concrete, `lax.switch`
    where it is traced."""
    if is_concrete(index):
        return branches[int(index)](*operands)
    return jax.lax.switch(index, branches, *operands)


def stage(pred, run):
    """`run()` where `pred` holds: eagerly `None` where it does not (nothing traced or
    compiled); under `jit` a `lax.cond` whose other branch is zeros of `run`'s shapes."""
    if is_concrete(pred):
        return run() if bool(pred) else None
    shapes = jax.eval_shape(run)
    zeros = lambda: jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)  # noqa: E731
    return jax.lax.cond(pred, run, zeros)


def latest(pred, new, old):
    """`new` where `pred` (its stage ran), else `old`: eagerly by `new is None`."""
    if new is None:
        return old
    if is_concrete(pred):
        return new
    return jax.tree.map(lambda a, b: jnp.where(pred, a, b), new, old)
