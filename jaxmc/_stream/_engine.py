r"""The streaming loop behind `integrate`: blocks, chunks, devices and tolerances.

The samples are organised in *blocks* of a fixed size $B$. Block $b$ draws its
randomness from `fold_in(key, b)` (randomised QMC: from its place in one
scrambled sequence), so the same evaluation index gets the same point whatever
the chunk size or the number of devices: a run is a function of `(key, n)`
alone, up to the rounding of the final reductions. Each loop step evaluates a
*chunk* of whole blocks, sharded over the devices of a `jax.sharding.Mesh`;
every device reduces its blocks to `Moments`, and the devices merge theirs with
collectives (`psum` of counts, weighted means and centred second moments). The
running total is another `Moments` merged with Chan et al.'s update, so memory
is bounded by the chunk and float32 stays accurate over $10^9$ samples.

Three kinds of statistical unit are used:

- Plain Monte Carlo, and importance sampling from a fixed proposal (the
  density `"auto"` fitted, `frozen`), treat every sample as an i.i.d. observation
  (for a mixture whose parts draw fixed shares, a conservative error bar: that
  stratification only lowers the variance).
- Stratification and VEGAS+ make the samples inside a block dependent; each
  block is one independent randomisation (an unbiased estimate on its own) and
  the variance comes from the spread of the block means.
- Randomised QMC keeps $R$ *replicas*, each one scrambled Sobol' sequence
  (carried through a trained VEGAS grid's map when `frozen` is one: `"auto"`'s
  `"grid_qmc"`, values $f(G(u))/q(G(u))$)
  walked block by block (block $b$ is block $\lfloor b/R \rfloor$ of replica
  $b \bmod R$). After $m$ blocks per replica each replica's mean is over the
  first $m B$ points of its sequence — at powers of two a whole $(t, s, d)$-net,
  where QMC's error falls like $O(n^{-1+\epsilon})$ or faster rather than the
  $n^{-1/2}$ of averaging many small nets — and the variance of the final mean
  $\bar I = \frac1R \sum_r \hat I_r$ is $s^2_R / R$ from the replicas' spread.
  With a tolerance the loop checks it only when each replica holds a power of
  two of points (QMCPy's `CubQMCNetG` and SciPy's `qmc_quad` sample nets the
  same way), from $2^{10}$ on, and stops when two checks in a row pass.

With a tolerance the first loop step's blocks are walked in up to
`MAX_EARLY_STEPS` smaller steps (`early_steps`), each followed by the check:
a tolerance that a few blocks meet stops there, not after a whole chunk, and
the steps after it are whole chunks again (on an accelerator, small steps
would leave it idle). Block means (stratified, VEGAS+ rounds) meet a
tolerance from `MIN_BLOCKS_TO_STOP` of them on.
"""

from __future__ import annotations

import math
import warnings
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import PartitionSpec

from .._checks import is_concrete
from .._compiled import per_integrand, per_shape
from .._diagnostics import ReliabilityWarning, bounded_variance, stderr_floor, variance_out_of_range
from .._integrand import evaluate
from .._progress import report
from .._stats import (
    Estimate,
    Moments,
    diagnosed,
    estimate_from_moments,
    merge,
    merge_across_devices,
    merge_all,
)
from ._blocks import Context, context, step_moments, step_points, values
from ._forecast import Forecast, forecast_note
from ._sizes import MIN_BLOCKS_TO_STOP, QMC_PASSES_TO_STOP


def at_rounding_floor(stderr: jax.Array, tail) -> jax.Array:
    """Whether a standard error is at the floor of its dtype's rounding error, which no
    budget lowers (`_diagnostics.stderr_floor`, where `diagnosed` floors eq. 13's error
    bar): a tolerance below it stops the stream there, unmet, rather than spending the rest
    of `max_n` (2^30 by default) on it. `tail`: the run's `Tail` (`None`: never)."""
    if tail is None:
        return jnp.zeros(jnp.shape(stderr), bool)
    return stderr <= stderr_floor(tail) * (1 + 1e-3)  # (just above it: as good as)


def stream_estimate(total: Moments, evaluations, bad, replicas: int, active=None) -> Estimate:
    """The estimate of a run's moments: i.i.d. units, or the spread of `replicas` means (the
    first `active` of them, where that is known only when the stream runs)."""
    if replicas == 1:
        return estimate_from_moments(total, evaluations, bad)
    means = total.mean
    if active is None:
        mean = jnp.mean(means, axis=0)
        var = jnp.sum((means - mean) ** 2, axis=0) / (replicas * (replicas - 1))
    else:
        used = jnp.reshape(jnp.arange(replicas) < active, (replicas,) + (1,) * (means.ndim - 1))
        count = active.astype(means.dtype)
        mean = jnp.sum(jnp.where(used, means, 0), axis=0) / count
        var = jnp.sum(jnp.where(used, (means - mean) ** 2, 0), axis=0) / (count * (count - 1))
        replicas = active
    var, conservative = bounded_variance(var, mean, total.tail)
    return Estimate(**diagnosed(mean, var, evaluations, bad, total.tail, conservative,
                                dof=replicas - 1))


def _local(ctx: Context, t, device, *, f, batched, sizes, per_step, devices):
    """Step `t` of device `device`'s blocks: `(its moments, evaluations, non-finite values)`."""
    x, points = step_points(ctx, t, device, sizes=sizes, per_step=per_step, devices=devices)
    return step_moments(ctx, evaluate(f, x, batched), points, sizes=sizes)


def _accumulate(carry, m, evaluations, bad):
    """The run's moments and counts with a step's added (Chan et al.'s merge)."""
    total, done, bad_total = carry
    return merge(total, m), done + evaluations, bad_total + bad


def _checked(t, carry, checks, rtol, atol, *, sizes, active=None):
    """The tolerance's checks after `t` steps, `checks = (the last one passed, the one
    before)`: updated where the tolerance is checked. Enough units to trust a variance
    estimate (two samples, or MIN_BLOCKS_TO_STOP block means: an early step may be one
    block); QMC only at powers of two per replica (whole nets), i.e. after 1, 2, 4, ...
    steps (each a power of two of rounds)."""
    if sizes.replicas == 1:
        per_sample = sizes.method in ("plain", "importance")
        at_check = carry[0].count >= (2 if per_sample else MIN_BLOCKS_TO_STOP)
    else:
        at_check = (t >= 1) & ((t & (t - 1)) == 0)
    est = stream_estimate(*carry, sizes.replicas, active)
    met = est.stderr <= jnp.maximum(atol, rtol * jnp.abs(est.mean))
    # A variance outside its dtype's range stays there (an overflowed sum of squares does
    # not come back): no budget meets the tolerance, as at the rounding floor.
    stuck = at_rounding_floor(est.stderr, carry[0].tail) | variance_out_of_range(est)
    passed = jnp.all(met | stuck)
    return tuple(jnp.where(at_check, new, old) for new, old in zip((passed, checks[0]), checks))


def _stops(checks, *, sizes):
    """Whether the checks stop the stream: QMC only when two in a row pass (nets of 2^k and
    2^(k+1) points: the spread of 8 small nets that fell low stopped runs early and low, a
    4-D camel at rtol=1e-3: 4 of 40 keys beyond 3 sigma)."""
    last, before = checks
    once = sizes.replicas == 1 or QMC_PASSES_TO_STOP == 1
    return last & (before | once)


@per_integrand
def stream(key, frozen, lo, hi, rtol, atol, budget=None, min_replicas=None, *, f, sizes, mesh,
           tolerant, progress, batched):
    """Evaluate `sizes.blocks` blocks (or fewer, once a tolerance is met) and reduce them;
    for `sizes.dynamic` QMC, those of `budget` evaluations in nets that `min_replicas` (at
    most `sizes.min_replicas`) fit in, both may be traced. One program (`stepwise` runs the
    same steps from Python, outside `jit`)."""
    ctx = context(key, frozen, lo, hi, budget, min_replicas, sizes=sizes)
    bar_total = None if tolerant else sizes.budget  # (a tolerance may stop it anywhere)

    def sharded(per_step):
        """Step `t` of `per_step` blocks: `(its moments, evaluations, non-finite values)`."""
        one = partial(_local, ctx, f=f, batched=batched, sizes=sizes, per_step=per_step,
                      devices=mesh.size)
        # One device needs no collectives (and `stream_on_mesh` no shard_map): compiles
        # stay short.
        return partial(one, device=0) if mesh.size == 1 else partial(_across_devices, one, mesh)

    start = _start(ctx, f, batched, sizes, mesh)
    zero = jnp.zeros((), jnp.int32)
    start, zero = jax.tree.map(partial(_carry_typed, mesh=mesh), (start, zero))

    def step(run_step, carry, t):
        carry = _accumulate(carry, *run_step(t))
        if progress:
            _report(stream_estimate(*carry, sizes.replicas, ctx.active), bar_total, mesh,
                    last=False)
        return carry

    if not tolerant:
        whole = sharded(sizes.per_step)
        if ctx.nblocks is not None and sizes.steps > 1:  # (steps past the budget's: skipped)
            run, empty = whole, (start, zero, zero)
            whole = lambda t: jax.lax.cond(t * sizes.per_step < ctx.nblocks, run,  # noqa: E731
                                           lambda _: empty, t)
        carry, _ = jax.lax.scan(
            lambda c, t: (step(whole, c, t), None), (start, zero, zero), jnp.arange(sizes.steps)
        )
    else:

        def walk(state, per_step, steps):
            """Steps of `per_step` blocks from `state = (steps done, carry, checks)` until
            the tolerance is met or `steps` are done."""
            run_step = sharded(per_step)

            def body(state):
                t, carry, checks = state
                carry = step(run_step, carry, t)
                return t + 1, carry, _checked(t + 1, carry, checks, rtol, atol, sizes=sizes)

            return jax.lax.while_loop(lambda s: (s[0] < steps) & ~_stops(s[2], sizes=sizes),
                                      body, state)

        no = _carry_typed(jnp.zeros((), bool), mesh)
        state = (zero, (start, zero, zero), (no, no))
        if sizes.early_steps > 1:
            # The first step's blocks in smaller steps (the same blocks, the same points);
            # after them the whole steps go on from the second, its checks again at 2, 4,
            # ... whole steps.
            state = walk(state, sizes.per_step // sizes.early_steps, sizes.early_steps)
            state = (zero + 1,) + state[1:]
        carry = walk(state, sizes.per_step, sizes.steps)[1]
    est = stream_estimate(*carry, sizes.replicas, ctx.active)
    if progress:  # (under a user's `jit`, this report closes the bar: `_progress`)
        _report(est, bar_total, mesh, last=True)
    return est


def stepwise(key, frozen, lo, hi, rtol, atol, budget=None, min_replicas=None, *, f, sizes,
             mesh, tolerant, progress, batched):
    """`stream` on one device, outside `jit`: the same steps, each as three programs run
    from Python, the points (`step_points`), the integrand's values (`values`, the only
    program compiled for each integrand) and their moments (`step_moments`), so that a new
    integrand compiles a small program where `stream` compiles the whole loop."""
    # (The programs below read the budget from `ctx`, not from their static sizes.)
    layout = sizes.per_block()
    budget, min_replicas = (None if a is None else jnp.asarray(a, jnp.int32)
                            for a in (budget if sizes.dynamic else sizes.budget, min_replicas))
    ctx = _context(key, frozen, lo, hi, budget, min_replicas, sizes=layout)
    total = None if tolerant else sizes.budget
    carry = None  # (zeros shaped as the first step's moments: tracing for them costs more)

    def step(carry, t, per_step):
        x, points = _points(ctx, jnp.int32(t), sizes=layout, per_step=per_step)
        m = _moments(ctx, values(x, f=f, batched=batched), points, sizes=layout)
        if carry is None:
            carry = _zeros_like(m)
        carry = _accumulate_compiled(carry, *m)
        if progress:
            est = _estimate(carry, ctx.active, sizes=layout)
            report(est.mean, est.stderr, est.n, total=total, last=False)
        return carry

    if not tolerant:
        steps = sizes.steps
        if ctx.nblocks is not None and sizes.steps > 1:  # (steps past the budget's: skipped)
            steps = min(steps, -(-int(ctx.nblocks) // sizes.per_step))
        for t in range(steps):
            carry = step(carry, t, sizes.per_step)
    else:
        no = np.asarray(False)
        t, checks = 0, (no, no)

        # QMC's error may fall like n^-3/2 on a smooth integrand; independent blocks' like
        # n^-1/2.
        forecast = Forecast(sizes.budget, 1.5 if sizes.replicas > 1 else 0.5)

        def walk(t, carry, checks, per_step, steps):
            while t < steps and not bool(_stops(checks, sizes=sizes)):
                carry = step(carry, t, per_step)
                t += 1
                checks = _check_compiled(jnp.int32(t), carry, checks, rtol, atol, sizes=layout)
                if sizes.replicas == 1 or t & (t - 1) == 0:  # (QMC: at whole nets)
                    est = _estimate(carry, ctx.active, sizes=layout)
                    _forecast(forecast, est, rtol, atol)
                    if progress:
                        report(est.mean, est.stderr, est.n, total=total, last=False,
                               note=forecast_note(forecast))
            return t, carry, checks

        if sizes.early_steps > 1:  # (as `stream`'s walks)
            _, carry, checks = walk(t, carry, checks, sizes.per_step // sizes.early_steps,
                                    sizes.early_steps)
            t = 1
        _, carry, _ = walk(t, carry, checks, sizes.per_step, sizes.steps)
    if carry is None:  # (no step ran)
        carry = _initial(ctx, sizes=sizes, f=f, batched=batched)
    est = _estimate(carry, ctx.active, sizes=layout)
    if progress:
        report(est.mean, est.stderr, est.n, total=total, last=True)
    return est


def _forecast(forecast: Forecast, est, rtol, atol) -> None:
    """Warn once, mid-run, where the forecast says the tolerance is out of the budget's reach."""
    if not all(is_concrete(a) for a in (est.mean, est.stderr, rtol, atol)):
        return  # (traced by a transformation run eagerly, `jax.jvp`: no values to read)
    text = forecast.unreachable(est.n, est.mean, est.stderr, est.dof, rtol, atol)
    if text is not None and not forecast.warned:
        forecast.warned = True
        warnings.warn(text, ReliabilityWarning, stacklevel=2)


# (The frozen density may hold Python numbers, a VEGAS+ allocation's strata: static, as
# `filter_jit` holds them. None of these programs evaluates the integrand.)
_context = per_shape(context)
_accumulate_compiled = jax.jit(_accumulate)
_check_compiled = per_shape(_checked)


@per_shape
def _points(ctx, t, *, sizes, per_step):
    return step_points(ctx, t, 0, sizes=sizes, per_step=per_step, devices=1)


@per_shape
def _moments(ctx, fx, points, *, sizes):
    return step_moments(ctx, fx, points, sizes=sizes)


@per_shape
def _estimate(carry, active, *, sizes):
    return stream_estimate(*carry, sizes.replicas, active)


def _initial(ctx, *, sizes, f, batched):
    """The empty carry a run starts from, as `stream`'s."""
    shapes = jax.eval_shape(lambda: _local(ctx, jnp.int32(0), 0, f=f, batched=batched,
                                           sizes=sizes, per_step=sizes.per_step, devices=1))
    return _zeros_like(shapes)


def _zeros_like(step):
    """The empty carry shaped as a step's `(moments, evaluations, non-finite values)`
    (NumPy zeros: no dispatch)."""
    moments, _, _ = step
    zero = np.zeros((), np.int32)
    return jax.tree.map(lambda s: np.zeros(s.shape, s.dtype), moments), zero, zero


def _start(ctx, f, batched, sizes, mesh):
    """The empty moments a run starts from (the shapes of a step's)."""
    shapes = jax.eval_shape(lambda: _local(ctx, jnp.int32(0), 0, f=f, batched=batched,
                                           sizes=sizes, per_step=sizes.per_step,
                                           devices=mesh.size)[0])
    return _empty_like(shapes)


def stream_on_mesh(key, frozen, lo, hi, rtol, atol, budget=None, min_replicas=None, *, f, mesh,
                   batched, **settings):
    """`stream`, each device of `mesh` running its share of the blocks under `shard_map`.

    The arrays enter `shard_map` as arguments, replicated: it may not close over
    arrays typed as sharded on `Explicit` mesh axes (a user's `jax.set_mesh`).
    An integrand that captures such arrays (its parameters, under `jit` or `vmap`
    in a mesh context) rules `shard_map` out: one program then runs every
    device's blocks, and the compiler places it (a `vmap`'s batch stays sharded).
    """
    args = (key, frozen, lo, hi, rtol, atol, budget, min_replicas)
    settings = dict(settings, f=f, mesh=mesh, batched=batched)
    if mesh.size == 1:
        if all(is_concrete(a) for a in jax.tree.leaves((args, f))):
            return stepwise(*args, **settings)
        return stream(*args, **settings)
    point = jnp.zeros((1,) + lo.shape, lo.dtype)
    captured = jax.make_jaxpr(lambda x: evaluate(f, x, batched))(point).consts
    typed = [m for m in map(_typed_mesh, captured) if m is not None]
    if typed:
        with jax.sharding.use_abstract_mesh(typed[0]):
            return stream(*args, **settings)
    return _sharded_stream(args, settings)


@per_integrand
def _sharded_stream(args, settings):
    """`stream(*args, **settings)` under `shard_map` over `settings["mesh"]`, taking its arrays
    (those of the integrand's `args` among them) as arguments."""
    arrays, static = eqx.partition((args, settings), eqx.is_array)

    def run(arrays):
        args, settings = eqx.combine(arrays, static)
        return stream(*args, **settings)

    return jax.shard_map(
        run, mesh=settings["mesh"], in_specs=PartitionSpec(), out_specs=PartitionSpec(),
    )(jax.tree.map(_replicated, arrays))


def _across_devices(local, mesh, t):
    """Step `t` of every device of `mesh`: `local(t, device)` on this device's blocks, merged by collectives.

    Run by `stream_on_mesh`'s `shard_map`, whose manual axes give the device.
    Axes that are not manual there (mapped away by a user's `vmap` of a batch
    sharded on them, or everywhere when `shard_map` was ruled out) are run here,
    device after device along them, so every block is still evaluated once.
    """
    device, manual, mapped = _this_device(mesh)
    if not mapped:
        m, evaluations, bad = local(t, device)
    else:
        grid = np.indices([size for size, _ in mapped]).reshape(len(mapped), -1)
        others = jnp.asarray(sum(i * stride for i, (_, stride) in zip(grid, mapped)), jnp.int32)
        m, evaluations, bad = jax.vmap(lambda other: local(t, device + other))(others)
        m, evaluations, bad = merge_all(m), *(jnp.sum(c, dtype=jnp.int32) for c in (evaluations, bad))
    if not manual:
        return m, evaluations, bad
    return merge_across_devices(m, manual), jax.lax.psum(evaluations, manual), jax.lax.psum(bad, manual)


def _this_device(mesh):
    """This device's row-major index over the manual axes of `mesh` (as `axis_index(axes)`),
    those axes, and the `(size, stride)` of the others (all of them outside `shard_map`)."""
    axes = tuple(mesh.axis_names)
    sizes = [mesh.shape[a] for a in axes]
    strides = [math.prod(sizes[i + 1 :]) for i in range(len(axes))]
    manual = tuple(a for a in axes if a in jax.sharding.get_abstract_mesh().manual_axes)
    device = sum((jax.lax.axis_index(a) * strides[axes.index(a)] for a in manual), jnp.int32(0))
    mapped = [(size, stride) for a, size, stride in zip(axes, sizes, strides) if a not in manual]
    return device, manual, mapped


def _typed_mesh(a):
    """The mesh of `a`'s type if it has `Explicit` axes (a sharding JAX tracks), else None."""
    if not isinstance(a, jax.Array):
        return None
    typed = jax.typeof(a).sharding.mesh
    return typed if jax.sharding.AxisType.Explicit in typed.axis_types else None


def _carry_typed(a, mesh):
    """`a` typed to start a loop carry in the caller's context: varying over the manual axes
    of a user's `shard_map` (the integrand's parameters may vary there), and replicated on an
    `Explicit` context mesh (so the sharded batch of a user's `vmap` can join it)."""
    context = jax.sharding.get_abstract_mesh()
    ours = set(mesh.axis_names) if mesh.size > 1 else set()
    manual = tuple(axis for axis in context.manual_axes if axis not in ours)
    if manual:
        a = jax.lax.pcast(a, manual, to="varying")
    if jax.sharding.AxisType.Explicit in context.axis_types:
        a = jax.sharding.reshard(a, PartitionSpec())
    return a


def _replicated(a):
    """`a` replicated over its mesh: a no-op unless its type shards it over `Explicit` axes."""
    sharding = jax.typeof(a).sharding
    if all(part is None for part in sharding.spec):
        return a
    return jax.sharding.reshard(a, sharding.update(spec=PartitionSpec()))


def _empty_like(shapes: Moments) -> Moments:
    return jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)


def _report(est: Estimate, total: int, mesh, last: bool) -> None:
    """Send the running estimate to the progress bar (`_progress.report`), from the first
    device: every device of a `shard_map` runs the loop."""
    send = partial(report, total=total, last=last)
    callback = partial(jax.debug.callback, send, est.mean, est.stderr, est.n)
    jax.lax.cond(_this_device(mesh)[0] == 0, callback, lambda: None)
