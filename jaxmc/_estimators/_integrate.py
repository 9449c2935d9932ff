r"""`integrate`: the streaming driver with tolerances, bounded memory and devices.

The samples are organised in *blocks* of a fixed size $B$. Block $b$ draws its
randomness from `fold_in(key, b)`, so the same evaluation index gets the same
point whatever the chunk size or the number of devices: a run is a function of
`(key, n)` alone, up to the rounding of the final reductions. Each loop step
evaluates a *chunk* of whole blocks, sharded over the devices of a
`jax.sharding.Mesh`; every device reduces its blocks to `Moments`, and the
devices merge theirs with collectives (`psum` of counts, weighted means and
centred second moments). The running total is another `Moments` merged with
Chan et al.'s update, so memory is bounded by the chunk and float32 stays
accurate over $10^9$ samples.

Two kinds of statistical unit are used. Plain Monte Carlo treats every sample
as an i.i.d. observation. Randomised QMC and stratification make the samples
inside a block dependent; there each block is one independent randomisation
(an unbiased estimate on its own) and the variance comes from the spread of
the block means, as in `randomized_qmc`.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from functools import partial
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec

from .. import _random
from .._box import to_box
from .._checks import (
    check_bounds,
    check_callable,
    check_choice,
    check_count,
    check_key,
    is_concrete,
)
from .._fit._vegas import strata_per_axis, stratified_unit_points
from .._integrand import evaluate, ratio
from .._points._registry import unit_points
from ..fit import Integrand, VegasPlus, run_adaptation
from ..proposals import Grid
from ..stats import (
    Estimate,
    Moments,
    block_moments,
    estimate_from_moments,
    merge,
    merge_across_devices,
    merge_all,
    stratified_estimate,
)


METHODS = ("auto", "plain", "qmc", "stratified", "adaptive")
ADAPT_ITERATIONS = 10  # VEGAS+ rounds that train the grid for method="adaptive" (at most)
ADAPT_BINS = 64  # grid bins per axis for method="adaptive"
BLOCK = 1 << 14  # samples per block; power of two so Sobol' blocks are (t, m, s)-nets
CHUNK = 1 << 18  # default samples per loop step (bounds memory)
MAX_N = 1 << 30  # default budget when only a tolerance is given
_QMC_MAX_DIM = 12  # measured in benchmarks/convergence.py up to d = 8; beyond, plain MC


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
) -> Estimate:
    r"""Integrate `f` over the box $[lo, hi]$ to a tolerance or a budget, streaming.

    Evaluates blocks of samples until
    $\mathrm{stderr} \le \max(\mathrm{atol}, \mathrm{rtol}\cdot|\mathrm{mean}|)$
    (for every component of an array-valued `f`) or until `n` evaluations
    (`max_n` when only a tolerance is given). With `n` alone it runs exactly
    `n` evaluations (rounded down to whole blocks for the block methods).

    **Arguments:**

    - `key`: a PRNG key; block $b$ uses `fold_in(key, b)`.
    - `f`: the integrand, written for one point (or batched with `batched=True`).
    - `lo`, `hi`: the box (scalars or shape `(d,)`).
    - `rtol`, `atol`: tolerances on the standard error; give either or both,
      and/or `n`.
    - `n`: the evaluation budget (a static int).
    - `method`: `"plain"` (i.i.d. uniform, eq. 8), `"qmc"` (each block a
      scrambled Sobol' net; variance from the spread of block means),
      `"stratified"` (each block a jittered grid), `"adaptive"` (VEGAS+: a
      `Grid` and its stratification trained by `jaxmc.fit.VegasPlus` on at most
      a quarter of the budget, then each block one VEGAS+ round of $2^{14}$
      points on the frozen grid and allocation; the budget is rounded down to
      whole rounds), or `"auto"`: scrambled Sobol'
      for $d \le 12$, where randomised QMC converges faster on smooth integrands
      and whose variance is at most a small constant times plain MC's (Owen), else plain.
    - `max_n`: the budget when only tolerances are given (default $2^{30}$).
    - `chunk`: samples evaluated per loop step (default $2^{18}$); bounds the
      memory and, with several devices, is split among them. Results do not
      depend on it beyond float rounding.
    - `nonfinite`: `"raise"` (default) raises `FloatingPointError` when some
      $f/p$ was not finite; `"drop"` lets those samples contribute zero (they
      are still counted in `n_nonfinite`).
    - `mesh`: a `jax.sharding.Mesh` whose devices share the blocks (default:
      all devices of the default backend).
    - `progress`: print the running estimate after every chunk.
    - `batched`: `f` receives the whole `(m, d)` batch.

    **Returns:** an `Estimate`.

    Without tolerances the loop has a fixed trip count and is differentiable;
    with tolerances it is a `while_loop` (forward-mode only).

    !!! Example

        ```python
        f = lambda x: jnp.exp(-jnp.sum(x**2))
        est = jaxmc.integrate(jax.random.key(0), f, [-3.0] * 4, [3.0] * 4, rtol=1e-4)
        ```
    """
    key = check_key(key)
    f = check_callable(f)
    lo, hi = check_bounds(lo, hi)
    method = check_choice(method, "method", METHODS)
    nonfinite = check_choice(nonfinite, "nonfinite", ("raise", "drop"))
    rtol = _check_tolerance(rtol, "rtol")
    atol = _check_tolerance(atol, "atol")
    if n is None and rtol is None and atol is None:
        raise ValueError("give a budget `n` or a tolerance `rtol`/`atol` to `integrate`.")
    if n is not None:
        n = check_count(n, "n")
        if max_n is not None:
            raise ValueError("give either `n` or `max_n` (the budget with tolerances), not both.")
    budget = n if n is not None else check_count(max_n if max_n is not None else MAX_N, "max_n")
    if budget >= 2**31:
        raise ValueError(f"the evaluation budget must be < 2**31, got {budget}.")
    chunk = check_count(chunk if chunk is not None else CHUNK, "chunk")
    if mesh is None:
        mesh = jax.make_mesh(
            (len(jax.devices()),), ("blocks",), axis_types=(jax.sharding.AxisType.Auto,)
        )
    elif not isinstance(mesh, Mesh):
        raise TypeError(f"`mesh` must be a jax.sharding.Mesh, got {type(mesh).__name__}.")
    d = 1 if lo.ndim == 0 else lo.shape[0]
    if method == "auto":
        method = "qmc" if d <= _QMC_MAX_DIM else "plain"
    proposal, trained = None, 0
    if method == "adaptive":
        block = _adaptive_block(budget)
        key, proposal, trained = _train_vegas_plus(key, f, lo, hi, budget, block, batched)
        budget -= trained
    plan = _plan(method, budget, chunk, mesh.devices.size, d, block if method == "adaptive" else 0)
    tolerant = rtol is not None or atol is not None
    est = _integrate(
        key,
        proposal,
        lo,
        hi,
        jnp.asarray(rtol if rtol is not None else 0.0, lo.dtype),
        jnp.asarray(atol if atol is not None else 0.0, lo.dtype),
        f=f,
        method=method,
        plan=plan,
        mesh=mesh,
        tolerant=tolerant,
        progress=progress,
        batched=batched,
    )
    if trained:
        est = Estimate(est.mean, est.variance, est.n + trained, est.n_nonfinite)
    if nonfinite == "raise":
        est = _raise_on_nonfinite(est)
    return est


def _adaptive_block(budget: int) -> int:
    """Points per VEGAS+ round of method="adaptive": 2^14, fewer for small budgets (>= 16 rounds)."""
    if budget < 16 * 256:
        raise ValueError(f"method='adaptive' needs a budget of at least {16 * 256}, got {budget}.")
    return min(BLOCK, 1 << int(math.floor(math.log2(budget // 16))))


def _train_vegas_plus(key, f, lo, hi, budget, block, batched):
    r"""Train a VEGAS+ grid and stratification on at most a quarter of the budget.

    Up to `ADAPT_ITERATIONS` rounds of `block` points (`jaxmc.fit.VegasPlus`:
    grid refinement and adaptive stratified sampling of the map's unit cube).
    Returns the streaming key, the frozen `(grid, counts, strata)` — the grid,
    the points per hypercube its last round allocated for the next, and the
    hypercubes per axis — and the number of training evaluations. Those are
    counted in the result's `n` but not in its mean, so the streamed estimate,
    drawn with the frozen grid and allocation, stays unbiased.
    """
    rounds = max(2, min(ADAPT_ITERATIONS, budget // (4 * block)))
    train_key, key = jax.random.split(key)
    rule = VegasPlus()
    grid = Grid(lo, hi, bins=ADAPT_BINS)
    _, state, _ = run_adaptation(rule, train_key, Integrand(f, batched), grid, rounds, block)
    strata = strata_per_axis(grid.dim, block, rule.max_strata)
    return key, (state.grid, state.draw.counts, strata), rounds * block


def _check_tolerance(tol: Any, name: str) -> Any:
    if tol is None:
        return None
    if is_concrete(tol):
        value = np.asarray(tol)
        if value.shape != () or not np.isfinite(value) or value < 0:
            raise ValueError(f"`{name}` must be a finite scalar >= 0, got {tol!r}.")
    return tol


def _raise_on_nonfinite(est: Estimate) -> Estimate:
    message = (
        "the integrand (divided by the density) was not finite at some samples; "
        "call integrate(..., nonfinite='drop') to let them contribute zero"
    )
    if is_concrete(est.n_nonfinite):
        count = int(est.n_nonfinite)
        if count:
            raise FloatingPointError(f"{message} ({count} of {int(est.n)} evaluations).")
        return est
    return eqx.error_if(est, est.n_nonfinite > 0, message + ".")


class _Plan(eqx.Module):
    """Static sizes of a run."""

    block: int = eqx.field(static=True)  # samples per block
    blocks: int = eqx.field(static=True)  # blocks in the budget
    budget: int = eqx.field(static=True)  # evaluations in the budget
    per_device: int = eqx.field(static=True)  # blocks per device per step
    steps: int = eqx.field(static=True)  # loop steps to exhaust the budget
    strata: tuple[int, ...] = eqx.field(static=True)  # jittered-grid counts per block


def _plan(
    method: str, budget: int, chunk: int, devices: int, d: int, adaptive_block: int = 0
) -> _Plan:
    strata: tuple[int, ...] = ()
    if method == "plain":
        # Smaller budgets get one power-of-two block, so little is masked away.
        block = min(BLOCK, 1 << max(0, math.ceil(math.log2(budget))))
        blocks = -(-budget // block)
    else:
        # Block methods need several blocks for a variance: at least 8.
        if budget < 16:
            raise ValueError(f"`n` must be >= 16 for method {method!r}, got {budget}.")
        block = min(BLOCK, 1 << int(math.floor(math.log2(budget // 8))))
        if method == "adaptive":  # one VEGAS+ round per block, of the size it was trained at
            block = adaptive_block
        if method == "stratified":
            per_axis = int(math.floor(block ** (1.0 / d) + 1e-9))
            if per_axis < 2:
                raise ValueError(
                    f"method='stratified' needs at least 2 strata per axis in a block of "
                    f"{block}, which d={d} does not allow; use method='qmc' or 'plain'."
                )
            strata = (per_axis,) * d
            block = per_axis**d
        blocks = budget // block
        budget = blocks * block
    per_step = min(max(1, -(-chunk // block)), blocks)  # never more blocks than the budget
    per_device = -(-per_step // devices)
    steps = -(-blocks // (per_device * devices))
    return _Plan(block, blocks, budget, per_device, steps, strata)


def _unit_points(method: str, plan: _Plan, key: jax.Array, d: int, dtype) -> jax.Array:
    """The block's points on the unit cube, shape `(block, d)`."""
    if method == "plain":
        return unit_points("uniform", key, plan.block, d, dtype=dtype)
    # Drawn in the default float dtype, then cast: this keeps the numbers of earlier
    # versions for float32 bounds under x64 (a float32 Sobol' draw truncates, not rounds).
    name = "sobol" if method == "qmc" else "stratified"
    return unit_points(name, key, plan.block, d, counts=plan.strata).astype(dtype)


def _vegas_plus_block(key, frozen, n, f, batched):
    r"""One VEGAS+ round on the frozen grid and allocation: one observation, its estimate.

    The round's points are jittered into the hypercubes of the grid's unit cube,
    `counts[h]` in cube $h$, mapped through the grid, and combined as
    $\hat I = v \sum_h \bar y_h$ (§4.2); the rounds are i.i.d., so the
    stream's variance comes from their spread.
    """
    grid, counts, strata = frozen
    raw = _random.uniform(key, (n, grid.dim), grid.lo.dtype)
    draw = stratified_unit_points(raw, counts, strata)
    x, log_p, _ = grid.map_with_bins(draw.u)
    fx = evaluate(f, x if grid.event_ndim else x[:, 0], batched)
    y, bad = ratio(fx, jnp.exp(log_p))
    bad_count = jnp.sum(bad, dtype=jnp.int32)
    est, _ = stratified_estimate(y, draw.cube, counts, 1.0 / counts.shape[0], bad_count)
    m = Moments(jnp.ones((), y.dtype), est.mean, jnp.zeros_like(est.mean))
    return m, jnp.asarray(n, jnp.int32), bad_count


@partial(
    eqx.filter_jit,
)
def _integrate(key, proposal, lo, hi, rtol, atol, *, f, method, plan, mesh, tolerant, progress, batched):
    d = 1 if lo.ndim == 0 else lo.shape[0]
    dtype = lo.dtype
    volume = jnp.prod(hi - lo)
    per_sample = method == "plain"
    axes = tuple(mesh.axis_names)

    def moments_of_block(b):
        if method == "adaptive":
            m, evaluations, bad = _vegas_plus_block(
                jax.random.fold_in(key, b), proposal, plan.block, f, batched
            )
            # Blocks past the budget (the last step's spare slots) are dropped.
            inside = b < plan.blocks
            m = jax.tree.map(lambda a: jnp.where(inside, a, jnp.zeros_like(a)), m)
            return m, jnp.where(inside, evaluations, 0), jnp.where(inside, bad, 0)
        else:
            u = _unit_points(method, plan, jax.random.fold_in(key, b), d, dtype)
            x = to_box(u if lo.ndim else u[:, 0], lo, hi)
            px = jnp.broadcast_to(1.0 / volume, (plan.block,))
        fx = evaluate(f, x, batched)
        y, bad = ratio(fx, px)
        index = b * plan.block + jnp.arange(plan.block)
        valid = index < plan.budget
        m = block_moments(y, valid)
        if not per_sample:
            # The block is one randomisation: one observation, its mean.
            m = Moments(jnp.where(m.count > 0, 1.0, 0.0).astype(dtype), m.mean, jnp.zeros_like(m.m2))
        return m, jnp.sum(valid, dtype=jnp.int32), jnp.sum(bad & valid, dtype=jnp.int32)

    single = mesh.devices.size == 1

    def local(t):
        # Device j of the mesh takes blocks [j * per_device, (j + 1) * per_device) of step t.
        device = 0 if single else jax.lax.axis_index(axes)
        first = (t * mesh.devices.size + device) * plan.per_device
        blocks = first + jnp.arange(plan.per_device, dtype=jnp.int32)
        m, evaluations, bad = jax.vmap(moments_of_block)(blocks)
        m = merge_all(m)
        evaluations, bad = jnp.sum(evaluations, dtype=jnp.int32), jnp.sum(bad, dtype=jnp.int32)
        if single:
            return m, evaluations, bad
        return merge_across_devices(m, axes), jax.lax.psum(evaluations, axes), jax.lax.psum(bad, axes)

    # One device needs no collectives; skipping shard_map there keeps compiles short.
    sharded = local if single else jax.shard_map(
        local, mesh=mesh, in_specs=PartitionSpec(), out_specs=PartitionSpec()
    )
    out_shape = jax.eval_shape(lambda: moments_of_block(jnp.int32(0))[0].mean).shape
    start = Moments(
        jnp.zeros((), dtype), jnp.zeros(out_shape, dtype), jnp.zeros(out_shape, dtype)
    )
    zero = jnp.zeros((), jnp.int32)

    def step(carry, t):
        total, evaluations, bad = carry
        m, e, b = sharded(t)
        total = merge(total, m)
        carry = (total, evaluations + e, bad + b)
        if progress:
            jax.debug.callback(_report, *_summary(carry, volume_free=True))
        return carry

    if not tolerant:
        carry, _ = jax.lax.scan(
            lambda c, t: (step(c, t), None), (start, zero, zero), jnp.arange(plan.steps)
        )
    else:

        def cond(state):
            t, carry = state
            est = _summary(carry)[1]
            tol = jnp.maximum(atol, rtol * jnp.abs(est.mean))
            # At least two units before trusting a variance estimate.
            converged = (carry[0].count >= 2) & jnp.all(est.stderr <= tol)
            return (t < plan.steps) & ~converged

        _, carry = jax.lax.while_loop(
            cond, lambda s: (s[0] + 1, step(s[1], s[0])), (zero, (start, zero, zero))
        )
    return _summary(carry)[1]


def _summary(carry, volume_free=False):
    total, evaluations, bad = carry
    est = estimate_from_moments(total, evaluations, bad)
    return (est.mean, est.stderr, evaluations) if volume_free else (None, est)


def _report(mean, stderr, evaluations):
    print(
        f"\rjaxmc.integrate: n={int(evaluations):,} mean={np.asarray(mean)} "
        f"stderr={np.asarray(stderr)}",
        end="",
        file=sys.stderr,
        flush=True,
    )
