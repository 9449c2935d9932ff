r"""`integrate`: the driver users reach for first — tolerances, budgets, and the choice of method.

The streaming itself (blocks, chunks, devices, the tolerance loop) is
`_stream.stream`; the pilot of `method="auto"` is `_auto.run_pilot`; what a
method does before its stream (train the VEGAS+ grid of `"adaptive"`, refit
auto's mixture) is `_runner.Runner`. This module checks the arguments, runs the
method and labels the result with the method used.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import AbstractMesh, AxisType, Mesh

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
from .._diagnostics import variance_out_of_range, warn_if_unreliable
from .._format import concrete
from .._integrand import bind
from .._stats import Estimate, ReliabilityWarning, estimate_fields
from ._adaptive import adaptive_block, is_fine, training_rounds
from ._auto import run_pilot, split_keys
from ._edged_grid import BENT_REPLICAS
from ._pilot_record import Pilot
from ._plan import PROBE_BUDGET, PROBE_REACH, QMC_REPLICAS
from ._runner import Runner
from ._tolerance import check_tolerance, unmet_tolerance


METHODS = ("auto", "plain", "qmc", "stratified", "adaptive")
CHUNK = 1 << 18  # default samples per loop step (bounds memory)
# ...for the stream from auto's mixture, whose density holds (points, components, d) arrays:
# in smaller steps they stay in cache (measured on a CPU at 1e6: 25-45% less time on a 4-D
# and an 8-D Gaussian peak and a 5-D posterior; QMC streams were 20-60% slower so).
MIXTURE_CHUNK = 1 << 16
MAX_N = 1 << 30  # default budget when only a tolerance is given


class IntegrationEstimate(Estimate):
    r"""What `integrate` returns: an `Estimate` that says how it was made.

    **Fields** (on top of `Estimate`'s):

    - `method`: the method that produced `mean` (for `"auto"`, the pilot's
      winner; `"auto"` itself only when the choice was traced under `jit`, where
      `pilot.choice` holds it).
    - `pilot`: for `"auto"`, the pilot's per-candidate figures (`Pilot`), else `None`.
    - `converged`: with a tolerance, whether the standard error met it (never where the
      variance left its dtype's range, `stats.unreliable`); else `None`.
    """

    method: str = eqx.field(static=True)
    pilot: Pilot | None
    converged: jax.Array | None


def integrate(
    key: jax.Array,
    f: Callable,
    lo: Any,
    hi: Any,
    *,
    rtol: float | None = None,
    atol: float | None = None,
    n: int | None = None,
    method: str = "auto",
    max_n: int | None = None,
    chunk: int | None = None,
    nonfinite: str = "raise",
    mesh: Mesh | None = None,
    progress: bool = False,
    batched: bool = False,
    args: Any = None,
) -> IntegrationEstimate:
    r"""Integrate `f` over the box $[lo, hi]$ to a tolerance or a budget, streaming.

    Evaluates blocks of samples until
    $\mathrm{stderr} \le \max(\mathrm{atol}, \mathrm{rtol}\cdot|\mathrm{mean}|)$
    (for every component of an array-valued `f`) or until `n` evaluations
    (`max_n` when only a tolerance is given). With `n` alone it runs at most
    `n` evaluations (rounded down to whole blocks for the block methods).

    **Arguments:**

    - `key`: a PRNG key; the result is a function of `(key, n)` alone, and of
      whether `"auto"` runs eagerly or under `jit`: eagerly its pilot skips
      what its figures already decide (a clear QMC win, a young grid far
      costlier than QMC, a mixture that could not win) and the stream gets
      the evaluations left; under `jit` every stage runs, so the budget can
      split differently (both estimates unbiased; where the eager pilot
      skipped nothing they agree). The ridge density (`"ridge_qmc"`, below)
      and the cube bent towards a singular corner (`"corner_qmc"`) are sought
      eagerly only.
    - `f`: the integrand, written for one point (or batched with `batched=True`).
    - `lo`, `hi`: the box (scalars or shape `(d,)`).
    - `rtol`, `atol`: tolerances on the standard error; give either or both,
      and/or `n`.
    - `n`: the evaluation budget (a static int).
    - `method`:
        - `"auto"` (default): a pilot measures each candidate's variance per
          evaluation — randomised QMC on at most 1/16 of the budget, then,
          unless QMC already beats plain MC 15-30-fold on the same points (a
          smooth integrand at that scale; where `f` is a product of
          one-dimensional factors, which a grid fits exactly, only by a far
          wider margin, on the nets' first quarter), the VEGAS+ grid of `"adaptive"` as
          it trains (at most a quarter), QMC's nets carried through the
          trained grid's map (`est.method` `"grid_qmc"`; where `f` is singular
          on a face of the box, as $x^{-1/2}$, its bins there follow the
          singularity's power, so that $f/q$ stays bounded) and a mixture of
          Gaussians seeded from the trained grid, with one more at each mode
          the grid missed that an ascent of $\log|f|$ from QMC's best points
          found (where JAX can differentiate `f`; `est.method` `"mixture"`,
          refitted to its own points when it wins, then streamed as
          importance sampling) — and spends the rest on the cheapest per
          unit of variance (see `jaxmc/_estimators/_auto.py` for the rules).
          Where QMC won no clear win and `f`'s gradients at QMC's largest
          values are all parallel, to some $w$, and `f` keeps its value a step
          across $w$ (a ridge function $g(w \cdot x)$: a resonance off the
          axes), it also measures QMC's nets through a density along $w$
          (`est.method` `"ridge_qmc"`: one coordinate drawn given the others
          from the profile $|g|$, read along the cube's diagonal, so that the
          integral over that coordinate is done nearly exactly; eagerly only).
          Where QMC's values or the grid's rounds have a power-law tail and
          `f` grows as a power of the distance to a corner of the box, as
          $(\sum_j x_j)^{-a}$ does at 0, it measures QMC's nets through the
          cube bent towards that corner, $x_j = z_j^p$ on the axes that meet
          there, with $p$ read off `f` along rays to it so that $f/q$ stays
          bounded (`est.method` `"corner_qmc"`; eagerly only);
          `est.method` names the winner and `est.pilot` keeps the figures.
          The pilot's evaluations count in `n` but not in the mean, which
          stays unbiased.
        - `"qmc"`: randomised QMC that keeps its convergence rate:
          $R$ independently scrambled Sobol' sequences, each walked block by
          block as one growing net; the mean is their average and the variance
          $s^2/R$ from their spread. With `n`, each replica gets the largest
          power of two of points that 3 replicas fit in and the rest of the
          budget buys more replicas ($R$ = 3…5); with a tolerance $R = 8$ and
          the stopping rule is checked when each replica holds a power of two
          of points, from $2^{10}$ on, and must pass twice in a row (at $2^k$
          and $2^{k+1}$: a spread of 8 small nets that fell low by chance
          stopped runs early and low). Few replicas make the error bar itself uncertain: it has
          `est.dof` $= R - 1$ degrees of freedom and `est.interval` is
          Student's $t$ interval (mean ± 2 stderr alone covers 82% at $R = 3$,
          91% at $R = 8$). On smooth integrands the error falls like $n^{-1}$
          or faster (plain Monte Carlo: $n^{-1/2}$); it is never much worse
          than plain MC (Owen's scrambled nets), in any dimension.
        - `"adaptive"`: VEGAS+ (`jaxmc.fit.VegasPlus`) in rounds of about
          budget/40 points (a power of two from 256 to $2^{14}$, each evaluated
          whole whatever `chunk`; the budget is rounded down to whole rounds)
          on a grid of 64 to 256 bins per axis: up to ten rounds on at most a quarter
          of the budget train a `Grid` and its stratification and are
          discarded; the rest of the rounds go on adapting, as vegas's do, and
          are averaged with weights growing with the round (fixed in advance,
          so the average stays unbiased), the error bar from their scatter. With a
          tolerance, the rounds may stop from the 16th on (fewer rounds'
          scatter is too uncertain an error bar), and after 32 the last grid
          streams on frozen
          (sharded over devices; the rounds before it, being sequential, are
          not) and that stream alone gives the result. See
          `jaxmc/_estimators/_adaptive.py`.
        - `"plain"` (i.i.d. uniform, eq. 8), `"stratified"` (each block a
          jittered grid; variance from the spread of block means).
    - `max_n`: the budget when only tolerances are given (default $2^{30}$),
      a cap rather than a size: the stream checks the tolerance from its
      first blocks on, and stops, unmet, where its error bar reaches the
      dtype's rounding floor (an `atol` below it; an `rtol` below it is
      refused), and with `rtol` `"auto"`'s pilot is first sized for
      $2^{17}$ evaluations (about $3\cdot10^4$ of them), sized anew for
      `max_n` only when its winner, a grid or a mixture, needs more than four
      times that for `rtol` (the probe's evaluations then count in `n`, not
      in `est.pilot`; measured, at `rtol=1e-2`: $10^4$ evaluations on a
      smooth 3-D integrand, $4.5\cdot10^4$ on $x^{-1/2}$, $5.5\cdot10^4$ on a
      4-D peak, where the pilot sized for $2^{30}$ took 0.27-0.33M). Under
      `jit`, where the figures are not known, the pilot is sized for `max_n`,
      as it is with `atol` alone; under `vmap` alone the probe's size stands
      when the figures are batched. `method="adaptive"` probes alike: it first
      trains its grid as for $2^{17}$ evaluations (ten rounds of $2^{11}$
      points, 64 bins per axis) and trains anew for `max_n` only when that
      grid needs more than twice $2^{17}$ for `rtol` (measured: $5.3\cdot10^4$
      evaluations at `rtol=1e-2` on a smooth 3-D integrand and a 4-D peak,
      where training for $2^{30}$ took $4.3\cdot10^5$ at any `rtol`).
    - `chunk`: samples evaluated per loop step (default $2^{18}$, $2^{16}$ for
      `"auto"`'s mixture); bounds the memory and, with several devices, is
      split among them (one block per device at least). Results do not depend
      on it beyond float rounding.
    - `nonfinite`: `"raise"` (default) raises `FloatingPointError` when some
      $f/p$ was not finite; `"drop"` lets those samples contribute zero (they
      are still counted in `n_nonfinite`, and `jaxmc.stats.unreliable` flags
      the result, but, dropped on request, they raise no warning).
    - `mesh`: a `jax.sharding.Mesh` whose devices share the blocks, over all
      its axes, whatever their names. Default: the context mesh of
      `jax.set_mesh`, else all devices of the default backend (of every
      process joined by `jax.distributed.initialize`). Inside a `shard_map`
      each device integrates on its own. An integrand that captures arrays
      sharded on `Explicit` mesh axes (under `jit` or `vmap` over sharded
      parameters) is run as one program, every device's blocks in it.
    - `progress`: show a progress bar (tqdm, on stderr) with the running
      estimate in the compact notation (`0.9977(42)`), moved after every
      chunk and closed where the evaluations stopped. Under `jit` the bar
      shows the streaming part only (opened and closed by the loop itself).
    - `batched`: `f` receives the whole `(m, d)` batch.
    - `args`: parameters of `f` (any pytree); if given, `f` is called as
      `f(x, args)`, as in optimistix and diffrax. Floats and NumPy values are
      traced; Python `int`s and `bool`s stay static (a new value compiles).

    **Returns:** an `IntegrationEstimate` (an `Estimate` with `method`, `pilot`
    and `converged`). Outside `jit`, a tolerance not met, within the budget or
    above the rounding floor, warns with `jaxmc.ReliabilityWarning`, saying which.

    Without tolerances the loop has a fixed trip count and is differentiable
    (in `args` too); with tolerances it is a `while_loop` (forward-mode only).
    A density fitted to `f`'s values (auto's grid or mixture, `"adaptive"`'s
    grid) is held fixed: the derivative is $\sum_i w_i\,\partial f(x_i)/q(x_i)$,
    an unbiased estimate of the integral's.

    **Compilation** is cached per integrand object `f` and sizes: a new
    `lambda` or closure per call compiles anew (for `"auto"` at $10^5$-$10^6$
    evaluations, in the `auto` benchmark on 2 CPU cores: 2.6-9 s where QMC
    wins, 4.3-15 s where the grid does, 6-19 s with the mixture). What does not
    evaluate `f` (the pilot's figures, the mixture's fits and draws) is
    compiled once per dimension and budget and serves the next integrand
    (a 4-D peak after another: 12.4-12.7 s -> 8.6-8.9 s). For a family
    of integrands define `f` once and pass the parameters in `args`: new
    values of the same shapes and dtypes reuse the compiled code (for
    `"auto"`, once each way the pilot can end). As under `jax.jit`, a global
    that `f` reads is frozen into that code.

    !!! Example

        ```python
        f = lambda x: jnp.exp(-jnp.sum(x**2))
        est = jaxmc.integrate(jax.random.key(0), f, [-3.0] * 4, [3.0] * 4, rtol=1e-4)
        print(est.mean, est.stderr, est.method)
        ```
    """
    key = check_key(key)
    f = bind(check_callable(f), args)
    lo, hi = check_bounds(lo, hi, finite_volume=True)
    method = check_choice(method, "method", METHODS)
    nonfinite = check_choice(nonfinite, "nonfinite", ("raise", "drop"))
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
    mixture_chunk = chunk or MIXTURE_CHUNK
    chunk = chunk or CHUNK
    mesh = _blocks_mesh(mesh)
    tolerant = rtol is not None or atol is not None
    # (An absent tolerance is a NumPy zero: an eager jnp constant costs ~30 us a call.)
    run = Runner(f, lo, hi, chunk, mesh, tolerant, progress, batched,
               *(np.zeros((), lo.dtype) if tol is None else jnp.asarray(tol, lo.dtype)
                 for tol in (rtol, atol)))
    pilot, spent = None, 0
    if method == "auto" and budget < _AUTO_MIN_BUDGET:
        if budget < 2 * QMC_REPLICAS:  # (plan's own message would name "qmc")
            raise ValueError(
                f"`{'n' if n is not None else 'max_n'}` must be >= {2 * QMC_REPLICAS} for method "
                f"'auto' (below {_AUTO_MIN_BUDGET} evaluations it runs QMC alone), got {budget}."
            )
        method = "qmc"  # too small a budget to share with a pilot
    # With only a tolerance, rtol among it, and outside jit, a pilot or a training is first
    # sized for PROBE_BUDGET (see there).
    probe = n is None and rtol is not None and is_concrete(rtol) and not _staged()
    probe_rtol = (float(np.asarray(rtol)) or None) if probe else None
    if method == "auto":
        key, pilot_keys = split_keys(key)
        pilot, state, mixture, rest, sized_rest, block, spent = _sized_pilot(
            pilot_keys, f, lo, hi, budget, batched, probe_rtol, tolerant
        )
        streams = dict(
            qmc=lambda: run.qmc(key, rest, spent),
            # The pilot trained the grid in full: refine and stream on it.
            # A fine grid (a power-law tail) refines finer (`tail_refining`).
            adaptive=lambda: run.trained_grid(key, rest, state, block, spent,
                                              tail=is_fine(state, lo.size)),
            # Scrambled Sobol' nets through the trained grid's map (bent where it follows a
            # singularity at a face, as the pilot measured it).
            grid_qmc=lambda: run.grid_qmc(key, rest, spent, state.grid),
            # Importance sampling from the mixture the pilot seeded from the grid (refitted
            # on a tenth of what the budget that sized the pilot left).
            mixture=lambda: run.mixture(key, rest, spent, *mixture, mixture_chunk, sized_rest),
            # Scrambled Sobol' nets through the pilot's ridge density (`state`: its map).
            ridge_qmc=lambda: run.qmc(key, rest, spent, grid=state),
            # ... and through the pilot's map bent towards a singular corner.
            corner_qmc=lambda: run.qmc(key, rest, spent, grid=state, min_replicas=BENT_REPLICAS),
        )
        branches = [streams[name] for name in pilot.candidates]
        if is_concrete(pilot.choice):
            method = pilot.candidates[int(pilot.choice)]
            est = branches[int(pilot.choice)]()
        else:  # chosen under jit: both streams are compiled, one runs
            est = jax.lax.switch(pilot.choice, branches)
    elif method == "adaptive":
        est = run.adaptive(key, budget, probe_rtol)
    else:
        est = run.block_method(method, key, budget)
    converged = out_of_range = None
    if tolerant:
        tol = jnp.maximum(run.atol, run.rtol * jnp.abs(est.mean))
        # (A variance out of its dtype's range meets nothing, however small it reads.)
        out_of_range = jnp.any(variance_out_of_range(est))
        converged = jnp.all(est.stderr <= tol) & ~out_of_range
    fields = estimate_fields(est)
    if spent:  # the pilot's evaluations count in n
        fields["n"] = est.n + spent
    est = IntegrationEstimate(**fields, method=method, pilot=pilot, converged=converged)
    if tolerant:
        est = _forward_mode_only(est)
    if nonfinite == "raise":
        est = _raise_on_nonfinite(est)
    # (Out of range, the reliability warning below says why, and what to do.)
    if tolerant and is_concrete(converged) and not bool(converged) and not bool(out_of_range):
        warnings.warn(unmet_tolerance(est, budget, run.rtol, run.atol, lo.dtype),
                      ReliabilityWarning, stacklevel=2)
    # (Values dropped on request, with nonfinite="drop", are not news.)
    fields = estimate_fields(est)
    if nonfinite == "drop":
        fields["n_nonfinite"] = jnp.zeros_like(est.n_nonfinite)
    warn_if_unreliable(Estimate(**fields), "integrate")
    return est


# Below this budget "auto" skips the pilot: a few thousand points cannot be shared.
_AUTO_MIN_BUDGET = 1 << 14


def _staged() -> bool:
    """Whether this call is being staged out (traced under `jit`)."""
    return not is_concrete(jnp.zeros(()))


def _sized_pilot(keys, f, lo, hi, budget, batched, rtol, tolerant):
    """`run_pilot` sized for `budget`, or, given `rtol` (a tolerance run outside `jit`), first
    for `PROBE_BUDGET` (see there). Returns `(Pilot, grid state, mixture, the stream's
    budget, what the budget that sized the pilot left of it, the pilot's round size,
    evaluations spent)`. The stream's budget is `budget` less the pilot's stages (as
    `run_pilot` counts them) and, when the pilot was sized anew, the probe's evaluations,
    which count in `n` (not in `pilot.evaluations`)."""
    probed = 0
    for sizing in ([min(budget, PROBE_BUDGET)] if rtol is not None else []) + [budget]:
        block = adaptive_block(sizing)
        rounds = training_rounds(sizing, block)
        pilot, state, mixture, rest = run_pilot(keys, f, lo, hi, sizing, batched, rounds, block,
                                                tolerant)
        if sizing == budget or not concrete(pilot):
            break
        choice = int(pilot.choice)
        need = float(pilot.variance_per_evaluation[choice]) / rtol**2
        if pilot.candidates[choice] == "qmc" or need <= PROBE_REACH * sizing:
            break  # (QMC's stream does not depend on the pilot's size)
        probed += sum(pilot.evaluations)
        keys = tuple(jax.random.fold_in(k, 1) for k in keys)
    stream = rest + (budget - sizing) - probed
    return pilot, state, mixture, stream, rest, block, probed + sum(pilot.evaluations)


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


