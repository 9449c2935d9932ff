r"""`integrate`: the driver users reach for first — tolerances, budgets, and the method.

A method is an object of `jaxmc.methods` (its options are fields); the strings are
aliases of default objects. This module checks the arguments, runs the method on the call's
`Problem` and labels the result: the method that streamed, and its plan.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable
from functools import partial
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import AbstractMesh, AxisType, Mesh

from .._auto._auto import Auto
from .._auto._pilot import STAGES, Pilot
from .._checks import (
    MAX_COUNT,
    check_bounds,
    check_callable,
    check_choice,
    check_count,
    check_flag,
    check_key,
    is_concrete,
)
from .._combine import combine
from .._compiled import release_if_crowded
from .._diagnostics import (
    reliability_reasons,
    trusted,
    variance_out_of_range,
    warn_if_unreliable,
)
from .._format import concrete
from .._integrand import bind
from .._methods._adaptive import Adaptive
from .._methods._basic import QMC, Plain, Stratified
from .._methods._grid_qmc import GridQMC
from .._methods._importance import Importance
from .._methods._mapped import Mapped
from .._methods._method import AbstractMethod, Problem
from .._methods._sequential import sequential_run
from .._stats import Estimate, ReliabilityWarning, estimate_fields
from .._stream._tolerance import check_tolerance, unmet_tolerance
from .._unbounded import axis_kinds, fit_maps, map_pilot_size, probe_count


# The strings `method` accepts, aliases of default method objects.
ALIASES: dict[str, AbstractMethod] = {
    "auto": Auto(), "plain": Plain(), "qmc": QMC(), "stratified": Stratified(),
    "adaptive": Adaptive(), "grid_qmc": GridQMC(), "importance": Importance(),
}
METHODS = tuple(ALIASES)
CHUNK = 1 << 18  # default samples per loop step (bounds memory)...
# ...and at most this many coordinates (a step's points, 8 MB in float64): in many
# dimensions a step's arrays otherwise leave the cache.
CHUNK_COORDINATES = 1 << 20
# ...for the stream from a mixture, whose density holds (points, components, d) arrays: in
# smaller steps they stay in cache (QMC's streams are faster in larger steps).
SMALL_CHUNK = 1 << 16
MAX_N = 1 << 30  # default budget when only a tolerance is given


class _Judged(Estimate):
    """What `integrate`'s verdict (`converged`, the warning) reads: the estimate, with values
    dropped on request not counted, and whether the integrand's tail is beyond its map."""

    tail_beyond_map: jax.Array | bool = False


def _beyond(est: Estimate, maps) -> jax.Array:
    """Whether the integral's share beyond the maps' reach exceeds `est`'s standard error."""
    return jnp.any(maps.beyond_reach * jnp.abs(est.mean) > est.stderr)


class IntegrationEstimate(Estimate):
    r"""What `integrate` returns: an `Estimate` that says how it was made.

    **Fields** (on top of `Estimate`'s):

    - `method`: the name of the method that produced `mean` (for `"auto"`, the pilot's
      winner; `"auto"` itself only when the choice was traced under `jit`, where
      `pilot.choice` holds it).
    - `plan`: the method that streamed, with what it trained (a grid, a fitted density): a
      pytree. `integrate(..., method=est.plan)` streams at once, without a pilot or
      training.
    - `pilot`: for `"auto"`, the pilot's record (`jaxmc.methods.Pilot`), else `None`.
    - `rounds`: where a VEGAS+ grid was trained (`"adaptive"`, `"grid_qmc"`,
      `"importance"`, `"auto"`'s grid stage), its training rounds: an `Estimate` stacked
      along its first axis, one per round, whose points adapted the grid and are not in
      `mean`; else `None`. `summary()` shows them as vegas's `summary()` shows its
      iterations.
    - `converged`: with a tolerance, whether the standard error met it and the diagnostics
      trust it (`stats.unreliable` of the estimate is False: never where no value was
      non-zero or the variance left its dtype's range); else `None`.
    - `nonfinite`: what `integrate` was asked to do with non-finite values, `"raise"`,
      `"drop"` or `"nan"`. Values dropped on request are counted in `n_nonfinite` but do
      not make the estimate unreliable.
    """

    method: str = eqx.field(static=True)
    plan: AbstractMethod
    pilot: Pilot | None
    rounds: Estimate | None
    converged: jax.Array | None
    nonfinite: str = eqx.field(default="raise", static=True)

    @property
    def tail_beyond_map(self) -> jax.Array | None:
        """With infinite limits, whether the share of the integral beyond the reach of the
        map of its infinite axes (`AxisMaps.beyond_reach`) exceeds the error bar
        (`jaxmc.stats.unreliable` then says so); else `None`."""
        maps = getattr(self.plan, "maps", None)
        return None if maps is None else _beyond(self, maps)

    def summary(self) -> str:
        """What made this estimate, as text (outside `jit`): the estimate and its counts, the
        method that streamed; for `"auto"` the pilot's race (each candidate's relative
        variance per evaluation, its uncertainty and cost, the winner) and the stages that
        ran; where a VEGAS+ grid was trained, its rounds with the running average's chi2/dof
        and Q; the tolerance's verdict; the diagnostics' reasons for distrust, if any."""
        if not concrete(self):
            raise ValueError("`summary()` needs concrete values: call it outside `jit`.")
        lines = [f"estimate: {self}  (n = {int(np.max(self.n)):,} evaluations)"]
        name = self.method
        if self.pilot is not None and name == "auto":  # (chosen under `jit`: the pilot knows)
            name = self.pilot.candidates[int(self.pilot.choice)]
        stream = f"method: {name}"
        if self.pilot is not None:
            stream += f", the winner of auto's pilot on {int(self.pilot.evaluations):,} of them"
        lines.append(stream)
        if self.pilot is not None:
            lines.append(self.pilot.table())
        trained = self.pilot is None or bool(np.asarray(self.pilot.stages)[STAGES.index("grid")])
        if self.rounds is not None and trained and jnp.ndim(self.rounds.n) == 1:
            lines.append("the grid's training rounds (VEGAS+, not in the estimate), averaged as "
                         "`jaxmc.fit.adapt` averages them:\neach weighed by the variance of the "
                         "round before it; a round of fewer than 10 effective\nsamples gets no "
                         "weight:")
            lines.append(combine(self.rounds, sequential=True).summary())
        dof = np.min(np.asarray(self.dof, float))
        lines.append("error bar: " + ("Gaussian (many degrees of freedom)" if not np.isfinite(dof)
                                      else f"Student's t, {dof:.0f} degrees of freedom")
                     + (", an i.i.d. upper bound (a power-law tail)"
                        if np.any(np.asarray(self.conservative)) else ""))
        if self.converged is not None:
            lines.append(f"tolerance: {'met' if bool(self.converged) else 'not met'}")
        reasons = reliability_reasons(self)
        lines.append("diagnostics: " + ("; ".join(reasons) if reasons else "nothing to report"))
        return "\n".join(lines)


def integrate(
    key: jax.Array,
    f: Callable,
    lo: Any,
    hi: Any,
    *,
    rtol: float | None = None,
    atol: float | None = None,
    n: int | None = None,
    method: str | AbstractMethod = "auto",
    max_n: int | None = None,
    chunk: int | None = None,
    nonfinite: str = "raise",
    mesh: Mesh | None = None,
    progress: bool = False,
    batched: bool = False,
    args: Any = None,
) -> IntegrationEstimate:
    r"""Integrate `f` over the box $[lo, hi]$ (limits may be infinite) to a tolerance or a
    budget, streaming.

    Evaluates blocks of samples until
    $\mathrm{stderr} \le \max(\mathrm{atol}, \mathrm{rtol}\cdot|\mathrm{mean}|)$
    (every component of an array-valued `f`) or until `n` evaluations (`max_n` with only
    a tolerance). The result is a function of `(key, n)` alone, the same eagerly and
    under `jit`. Under `vmap` the members run one after another, as a loop would (`"auto"`
    with a pilot and a choice for each).

    **Arguments:**

    - `key`: a PRNG key.
    - `f`: the integrand, written for one point (or for a batch with `batched=True`).
    - `lo`, `hi`: the box (scalars or shape `(d,)`). Limits may be infinite (`-jnp.inf` in
      `lo`, `jnp.inf` in `hi`, constants under `jit`): each infinite axis is then mapped
      onto a finite interval by a map fitted to `f` (its centre and scale to where $|f|$
      has its mass, its power tail to how fast $|f|$ decays, so that $f$ times the
      Jacobian stays bounded; see `jaxmc.methods.Mapped`), on a few thousand evaluations
      that count in `n`, and `method` streams on the finite box.
    - `rtol`, `atol`: tolerances on the standard error; give either or both, and/or `n`.
    - `n`: the evaluation budget (a static int); with a tolerance too, a cap. At least 95% of
      it is spent (whole nets and blocks; the result's `n` says how many).
    - `method`: a method of `jaxmc.methods`, or its name: `"auto"` (default: a pilot races
      QMC, the VEGAS+ grid, QMC through the grid and a mixture seeded from it; see
      `jaxmc.methods.Auto`), `"qmc"`, `"adaptive"`, `"grid_qmc"`, `"importance"`, `"plain"`,
      `"stratified"`; or a plan from an earlier result, `est.plan`, which streams at once.
    - `max_n`: the budget when only tolerances are given (default $2^{30}$): a cap, not a
      size; the stream also stops, unmet, where its error bar reaches the dtype's rounding
      floor. Outside `jit`, a run whose error bar, at the rate it has fallen so far, cannot
      meet the tolerance within the budget warns as soon as that is clear (and `progress`
      shows the forecast).
    - `chunk`: samples evaluated per loop step (default $2^{18}$, fewer in more than four
      dimensions, at most $2^{20}$ coordinates; $2^{16}$ at most from a mixture): bounds
      the memory; results do not depend on it beyond float rounding.
    - `nonfinite`: `"raise"` (default) raises `FloatingPointError` when some $f/p$ was not
      finite (under `jit`, a runtime error); `"drop"` lets those samples contribute zero
      (counted in `n_nonfinite`); `"nan"` makes the estimate NaN (mean and variance;
      counted, and `stats.unreliable` says why). Under `jit` the runtime error of `"raise"`
      is a host callback, and JAX's persistent compilation cache does not keep programs
      that hold one: `"drop"` or `"nan"` lets a re-run script start warm.
    - `mesh`: a `jax.sharding.Mesh` whose devices share the blocks (default: the context
      mesh of `jax.set_mesh`, else all devices of the default backend).
    - `progress`: show a progress bar (tqdm) with the running estimate.
    - `batched`: `f` receives the whole `(m, d)` batch.
    - `args`: parameters of `f` (any pytree), passed as `f(x, args)`: new values of the same
      shapes reuse the compiled code.

    **Returns:** an `IntegrationEstimate`: an `Estimate` with `method`, `plan`, `pilot` and
    `converged`. Outside `jit`, an unmet tolerance or an untrustworthy error bar warns with
    `jaxmc.ReliabilityWarning`.

    Without tolerances the loop has a fixed trip count and is differentiable (in `args`
    too); with tolerances it is a `while_loop` (forward mode only). A density fitted to `f`
    is held fixed: the derivative is $\sum_i w_i\,\partial f(x_i)/q(x_i)$, an unbiased
    estimate of the integral's.

    !!! Example

        ```python
        f = lambda x: jnp.exp(-jnp.sum(x**2))
        est = jaxmc.integrate(jax.random.key(0), f, [-3.0] * 4, [3.0] * 4, rtol=1e-4)
        print(est, est.method)
        ```
    """
    key = check_key(key)
    f = bind(check_callable(f), args)
    kinds = axis_kinds(lo, hi)
    lo, hi = check_bounds(lo, hi, finite_volume=True, infinite=True)
    method = _method(method)
    if isinstance(method, Mapped) and (kinds is None or method.maps.kinds != kinds):
        raise ValueError(
            "`method` is a plan made for infinite limits on other axes or sides: it streams "
            "only where `lo` and `hi` are infinite where they were.")
    if kinds is not None and method.trained and not isinstance(method, Mapped):
        raise ValueError(
            "`method` is a plan made on a finite box, and `lo`/`hi` hold infinite limits; "
            "pass the method's name (e.g. 'auto') to fit a map of the infinite axes.")
    nonfinite = check_choice(nonfinite, "nonfinite", ("raise", "drop", "nan"))
    rtol = check_tolerance(rtol, "rtol", lo.dtype)
    atol = check_tolerance(atol, "atol", lo.dtype)
    progress = check_flag(progress, "progress")
    batched = check_flag(batched, "batched")
    if n is None and rtol is None and atol is None:
        raise ValueError("give a budget `n` or a tolerance `rtol`/`atol` to `integrate`.")
    if n is not None:
        n = check_count(n, "n")
        if max_n is not None:
            raise ValueError("give either `n` or `max_n` (the budget with tolerances), not both.")
    budget = n if n is not None else check_count(max_n if max_n is not None else MAX_N, "max_n")
    if budget > MAX_COUNT:
        raise ValueError(
            f"the evaluation budget `{'n' if n is not None else 'max_n'}` must be at most "
            f"2**31 - 1 (counts are int32), got {budget}."
        )
    chunk = check_count(chunk, "chunk") if chunk is not None else None
    tolerant = rtol is not None or atol is not None
    # (An absent tolerance is a NumPy zero: an eager jnp constant costs ~30 us a call.)
    rtol, atol = (np.zeros((), lo.dtype) if tol is None else jnp.asarray(tol, lo.dtype)
                  for tol in (rtol, atol))
    release_if_crowded(key, lo, hi, f)
    default = default_chunk(1 if lo.ndim == 0 else lo.shape[0])
    problem = Problem(f, lo, hi, batched, chunk or default, _blocks_mesh(mesh), tolerant,
                      progress, rtol, atol, chunk or min(default, SMALL_CHUNK), probe=n is None)
    probes = 0
    if kinds is not None and not isinstance(method, Mapped):
        key, key_maps = jax.random.split(key)
        pilot_size = map_pilot_size(problem.pilot_budget(budget))
        probes = probe_count(kinds, pilot_size)
        if 4 * probes > budget:
            raise ValueError(
                f"with infinite limits `integrate` spends {probes} evaluations fitting a map of "
                f"the infinite axes; give a budget of at least {4 * probes}, got {budget}.")
        maps = fit_maps(key_maps, f, lo, hi, kinds=kinds, pilot=pilot_size, batched=batched)
        method = Mapped(method, jax.lax.stop_gradient(maps))
    # Under `vmap` a method (`auto`'s pilot and stream included) runs element after element.
    run = method.run if progress else partial(sequential_run, method)
    est, plan, pilot, rounds = run(key, problem, budget - probes)
    if probes:
        est = dataclasses.replace(est, n=est.n + probes)
    # (Values dropped on request, with nonfinite="drop", are not news.)
    maps = getattr(plan, "maps", None)
    judged = _Judged(**estimate_fields(est),
                     tail_beyond_map=False if maps is None else _beyond(est, maps))
    if nonfinite == "drop":
        judged = eqx.tree_at(lambda e: e.n_nonfinite, judged, jnp.zeros_like(est.n_nonfinite))
    met = converged = None
    if tolerant:
        # One verdict: a tolerance met by an error bar the diagnostics distrust (a variance
        # out of its dtype's range, no non-zero value seen, ...) is not converged.
        met = problem.met(est)
        converged = met & trusted(judged)
    streamed = plan.method if isinstance(plan, Mapped) else plan
    name = streamed.name if is_concrete(getattr(streamed, "choice", 0)) else "auto"
    est = IntegrationEstimate(**estimate_fields(est), method=name, plan=plan, pilot=pilot,
                              rounds=rounds, converged=converged, nonfinite=nonfinite)
    if tolerant:
        est = _forward_mode_only(est)
    if nonfinite == "raise":
        est = _raise_on_nonfinite(est)
    elif nonfinite == "nan":
        est = _nan_on_nonfinite(est)
    # (Out of range, the reliability warning below says why, and what to do.)
    if (tolerant and is_concrete(met) and not bool(met)
            and not bool(jnp.any(variance_out_of_range(est)))):
        warnings.warn(unmet_tolerance(est, budget, rtol, atol, lo.dtype),
                      ReliabilityWarning, stacklevel=2)
    warn_if_unreliable(judged, "integrate")
    return est


def default_chunk(d: int) -> int:
    """Samples per loop step by default in `d` dimensions: `CHUNK`, or the largest power of
    two whose points hold at most `CHUNK_COORDINATES` coordinates."""
    return min(CHUNK, 1 << (CHUNK_COORDINATES // d).bit_length() - 1)


def _method(method: Any) -> AbstractMethod:
    """`method` as an object: a name's default object, or a method object itself."""
    if isinstance(method, AbstractMethod):
        return method
    if isinstance(method, str) and method in ALIASES:
        return ALIASES[method]
    raise ValueError(
        f"`method` must be one of {METHODS} or a method object of jaxmc.methods (an earlier "
        f"result's `plan` among them), got {method!r}."
    )


def _blocks_mesh(mesh: Mesh | None) -> Mesh | AbstractMesh:
    """The mesh whose devices share the blocks: `mesh`, else the context mesh of
    `jax.set_mesh` (all its axes), else all devices of the default backend."""
    context = jax.sharding.get_abstract_mesh()
    if mesh is not None:
        if not isinstance(mesh, Mesh):
            raise TypeError(f"`mesh` must be a jax.sharding.Mesh, got {type(mesh).__name__}.")
        if not context.empty and mesh.abstract_mesh != context:
            raise ValueError(
                f"`mesh` {mesh} differs from the context mesh {context} set by jax.set_mesh; "
                "pass mesh=None to share the blocks over the context mesh."
            )
        return mesh
    if context.empty:
        return jax.make_mesh((len(jax.devices()),), ("blocks",), axis_types=(AxisType.Auto,))
    if context.manual_axes:
        # Inside a user's shard_map every device integrates on its own.
        return AbstractMesh((1,), ("blocks",))
    return context


_NONFINITE_MESSAGE = (
    "jaxmc.integrate: f(x)/p(x) was not finite (NaN or inf) at some samples, so the "
    "estimate would be meaningless. Typically `f` has a singularity or is evaluated outside "
    "its domain (a log or sqrt of a negative number). Fix `f` there (e.g. with jnp.where), or "
    "pass nonfinite='drop' to let those samples contribute zero; they are then counted in "
    "the result's `n_nonfinite`."
)


def _raise_on_nonfinite(est: Estimate) -> Estimate:
    """`FloatingPointError` with the count outside `jit`; under `jit` a runtime error
    (`eqx.error_if`) whose text carries the same message (under `jax.jit` inside a
    `JaxRuntimeError`; `equinox.filter_jit` raises it cleanly)."""
    if is_concrete(est.n_nonfinite):
        count = int(est.n_nonfinite)
        if count:
            raise FloatingPointError(
                f"{_NONFINITE_MESSAGE} ({count:,} of {int(est.n):,} evaluations were not finite.)"
            )
        return est
    return eqx.error_if(est, est.n_nonfinite > 0, _NONFINITE_MESSAGE)


def _nan_on_nonfinite(est: Estimate) -> Estimate:
    """`est` with its mean and variance NaN where some value was not finite: no runtime
    check, so a program under `jit` holds no host callback."""
    bad = est.n_nonfinite > 0
    return dataclasses.replace(est, mean=jnp.where(bad, jnp.nan, est.mean),
                               variance=jnp.where(bad, jnp.nan, est.variance))


_REVERSE_MODE_MESSAGE = (
    "jaxmc.integrate: reverse-mode differentiation (jax.grad, jax.vjp) needs a fixed sample "
    "count, and a run with a tolerance `rtol`/`atol` stops when the tolerance is met (a "
    "while_loop, which JAX cannot differentiate backwards). Pass `n=` without `rtol`/`atol`, "
    "or differentiate in forward mode (jax.jvp, jax.jacfwd), which works with tolerances."
)


def _forward_mode_only(est: Estimate) -> Estimate:
    """A tolerance run's result, through an identity whose transpose raises `_REVERSE_MODE_MESSAGE`.

    Reverse mode transposes from the outputs back, so `jax.grad` stops here, at
    trace time, before it reaches the tolerance loop; forward mode passes through.
    """
    floats, rest = eqx.partition(est, eqx.is_inexact_array)
    floats = eqx.internal.nondifferentiable_backward(floats, msg=_REVERSE_MODE_MESSAGE)
    return eqx.combine(floats, rest)


