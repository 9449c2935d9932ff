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
tolerance from `MIN_BLOCKS_TO_STOP` of them on. Coverage measured with 60
keys on 6 integrands (a 4-D camel, a 3-D ball, an 8-D half-space, a 2-D
discontinuity, an 8-D Gaussian, an annulus) at `rtol` 1e-2 and 1e-3 with QMC:
2-sigma 0.87-0.98, 5 of 720 runs beyond 3 sigma (Student's t with 7 degrees
of freedom: 14 expected), as with the first check at nets of 2^14 (8 of 720),
at an 8th of the evaluations on the easy cases (16384).
"""

from __future__ import annotations

import math
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import PartitionSpec

from .. import _random
from .._box import to_box
from .._compiled import per_integrand
from .._diagnostics import bounded_variance, stderr_floor, variance_out_of_range
from .._fit._vegas import stratified_unit_points
from .._integrand import evaluate, ratio
from .._points._common import uint32_to_unit
from .._points._registry import unit_points
from .._points._sobol import sobol_block, sobol_scramble
from .._progress import report
from .._stats import (
    Estimate,
    Moments,
    block_moments,
    diagnosed,
    estimate_from_moments,
    merge,
    merge_across_devices,
    merge_all,
    tail_of,
)
from ._sizes import MIN_BLOCKS_TO_STOP, QMC_PASSES_TO_STOP


def replica_points(scramble, position, log2_size: int, dtype) -> jax.Array:
    """Block `position` (`2**log2_size` points on $[0,1)^d$) of the Sobol' sequence
    scrambled by `scramble = sobol_scramble(key, d)`: one QMC replica's next net block."""
    return uint32_to_unit(sobol_block(*scramble, position, log2_size), dtype, centred=True)


def at_rounding_floor(stderr: jax.Array, tail) -> jax.Array:
    """Whether a standard error is at the floor of its dtype's rounding error, which no
    budget lowers (`_diagnostics.stderr_floor`, where `diagnosed` floors eq. 13's error
    bar): a tolerance below it stops the stream there, unmet, rather than spending the rest
    of `max_n` (2^30 by default) on it. `tail`: the run's `Tail` (`None`: never)."""
    if tail is None:
        return jnp.zeros(jnp.shape(stderr), bool)
    return stderr <= stderr_floor(tail) * (1 + 1e-3)  # (just above it: as good as)


def _vegas_plus_block(key, frozen, n, f, batched):
    r"""One VEGAS+ round on the frozen grid and allocation: one observation, its estimate.

    The round's points are jittered into the hypercubes of the grid's unit cube,
    `counts[h]` in cube $h$, mapped through the grid, and combined as
    $\hat I = v \sum_h \bar y_h$ (§4.2, as `stats.stratified_estimate`); the rounds are i.i.d., so the
    stream's variance comes from their spread.
    """
    grid, counts, strata = frozen
    raw = _random.uniform(key, (n, grid.dim), grid.lo.dtype)
    draw = stratified_unit_points(raw, counts, strata)
    x, log_p, _ = grid.map_with_bins(draw.u)
    fx = evaluate(f, x if grid.event_ndim else x[:, 0], batched)
    y, bad = ratio(fx, jnp.exp(log_p))
    # Only the mean is needed (the stream's variance comes from the rounds' spread):
    # v sum_h mean_h = v sum_i y_i / n_{h(i)}, with no per-hypercube reduction.
    per_point = 1.0 / (counts.shape[0] * jnp.maximum(counts, 1).astype(y.dtype))[draw.cube]
    mean = jnp.sum(y * jnp.reshape(per_point, (-1,) + (1,) * (y.ndim - 1)), axis=0)
    # The diagnostics are of the values y = f/p (as `stats.stratified_estimate`'s).
    m = Moments(jnp.ones((), y.dtype), mean, jnp.zeros_like(mean), tail_of(y))
    return m, jnp.asarray(n, jnp.int32), jnp.sum(bad, dtype=jnp.int32)


def _one_hot_moments(m: Moments, slot: jax.Array, slots: int) -> Moments:
    """Place a block's moments in row `slot` of `slots` rows (the others empty)."""
    hot = jnp.arange(slots) == slot
    count = jnp.where(hot, m.count, 0.0).astype(m.mean.dtype)

    def place(a):
        return jnp.where(jnp.reshape(hot, (slots,) + (1,) * a.ndim), a[None], jnp.zeros_like(a)[None])

    return Moments(count, place(m.mean), place(m.m2), m.tail)


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


@per_integrand
def stream(key, frozen, lo, hi, rtol, atol, budget=None, min_replicas=None, *, f, sizes, mesh,
           tolerant, progress, batched):
    """Evaluate `sizes.blocks` blocks (or fewer, once a tolerance is met) and reduce them;
    for `sizes.dynamic` QMC, those of `budget` evaluations in nets that `min_replicas` (at
    most `sizes.min_replicas`) fit in, both may be traced."""
    method = sizes.method
    d = 1 if lo.ndim == 0 else lo.shape[0]
    dtype = lo.dtype
    volume = jnp.prod(hi - lo)
    per_sample = method in ("plain", "importance")
    bar_total = None if tolerant else sizes.budget  # (a tolerance may stop it anywhere)
    if method == "qmc":
        scrambles = jax.vmap(lambda k: sobol_scramble(k, d))(
            jax.random.split(key, sizes.replicas)
        )
        log2_block = sizes.block.bit_length() - 1
    active = nblocks = None
    if sizes.dynamic:
        # Nets of the largest power of two of points that `min_replicas` fit in the budget,
        # as many replicas as fit; each walked block by block, replica after replica.
        budget = jnp.asarray(budget, jnp.int32)
        fewest = sizes.min_replicas if min_replicas is None else min_replicas
        net = jnp.left_shift(1, 31 - jax.lax.clz(budget // fewest))
        active, per_replica = budget // net, net // sizes.block
        nblocks = active * per_replica

    def replica_of(b):
        """A QMC block's replica and its position in the replica's net."""
        if sizes.dynamic:
            return b // per_replica, b % per_replica
        return b % sizes.replicas, b // sizes.replicas

    def points_of_block(b):
        """The block's points `x` and their density `p(x)`."""
        if method == "importance":  # from the frozen proposal
            return frozen.sample(jax.random.fold_in(key, b), sizes.block)
        if method == "qmc":
            r, position = replica_of(b)
            u = replica_points((scrambles[0][r], scrambles[1][r]), position, log2_block, dtype)
            if frozen is not None:  # scrambled nets through a trained grid's map
                x, log_p = frozen.map(u)
                return (x if frozen.event_ndim else x[:, 0]), jnp.exp(log_p)
        elif method == "plain":
            u = unit_points("uniform", jax.random.fold_in(key, b), sizes.block, d, dtype=dtype)
        else:
            # Drawn in the default float dtype, then cast: this keeps the numbers of earlier
            # versions for float32 bounds under x64 (a float32 draw truncates, not rounds).
            u = unit_points(
                "stratified", jax.random.fold_in(key, b), sizes.block, d, counts=sizes.strata
            ).astype(dtype)
        x = to_box(u if lo.ndim else u[:, 0], lo, hi)
        return x, jnp.broadcast_to(1.0 / volume, (sizes.block,))

    def moments_of_block(b, inside):
        if method == "adaptive":
            m, evaluations, bad = _vegas_plus_block(
                jax.random.fold_in(key, b), frozen, sizes.block, f, batched
            )
            # Slots past the budget (the last step's spare ones) are dropped.
            m = jax.tree.map(lambda a: jnp.where(inside, a, jnp.zeros_like(a)), m)
            return m, jnp.where(inside, evaluations, 0), jnp.where(inside, bad, 0), None
        x, px = points_of_block(b)
        fx = evaluate(f, x, batched)
        y, bad = ratio(fx, px)
        index = b * sizes.block + jnp.arange(sizes.block)
        valid = (index < sizes.budget if nblocks is None else index < nblocks * sizes.block) & inside
        m = block_moments(y, valid, with_tail=False)  # the step's tail comes from all its blocks
        if not per_sample:
            # The block is one randomisation: one observation, its mean.
            unit = jnp.where(m.count > 0, 1.0, 0.0).astype(dtype)
            m = Moments(unit, m.mean, jnp.zeros_like(m.m2), m.tail)
        if method == "qmc":
            # Its replica's running mean weighs it by its points.
            m = _one_hot_moments(m._replace(count=m.count * sizes.block), replica_of(b)[0],
                                 sizes.replicas)
        evaluations = jnp.sum(valid, dtype=jnp.int32)
        return m, evaluations, jnp.sum(bad & valid, dtype=jnp.int32), (y, valid)

    def local(t, device, per_step):
        # Device j takes slots [j * per_device, (j + 1) * per_device) of step t's blocks.
        per_device = -(-per_step // mesh.size)
        slot = device * per_device + jnp.arange(per_device, dtype=jnp.int32)
        blocks = t * per_step + slot
        inside = (slot < per_step) & (blocks < sizes.blocks)
        m, evaluations, bad, values = jax.vmap(moments_of_block)(blocks, inside)
        m = merge_all(m)
        if values is not None:
            # One search for the largest values among all the step's blocks: a block's own
            # search and the merges of their tails cost twice as much (on a CPU).
            y, valid = jax.tree.map(lambda a: jnp.reshape(a, (-1,) + a.shape[2:]), values)
            m = m._replace(tail=tail_of(y, valid))
        return m, jnp.sum(evaluations, dtype=jnp.int32), jnp.sum(bad, dtype=jnp.int32)

    def sharded(per_step):
        """Step `t` of `per_step` blocks: `(its moments, evaluations, non-finite values)`."""
        # One device needs no collectives (and `stream_on_mesh` no shard_map): compiles
        # stay short.
        one = partial(local, per_step=per_step)
        return partial(one, device=0) if mesh.size == 1 else partial(_across_devices, one, mesh)

    start = _empty_like(jax.eval_shape(lambda: local(jnp.int32(0), 0, sizes.per_step)[0]))
    zero = jnp.zeros((), jnp.int32)
    start, zero = jax.tree.map(partial(_carry_typed, mesh=mesh), (start, zero))

    def step(run_step, carry, t):
        total, evaluations, bad = carry
        m, e, b = run_step(t)
        carry = (merge(total, m), evaluations + e, bad + b)
        if progress:
            _report(stream_estimate(*carry, sizes.replicas, active), bar_total, mesh, last=False)
        return carry

    if not tolerant:
        whole = sharded(sizes.per_step)
        if nblocks is not None:  # (the steps past the budget's blocks are skipped)
            run = whole
            empty = (start, zero, zero)
            whole = lambda t: jax.lax.cond(t * sizes.per_step < nblocks, run,  # noqa: E731
                                           lambda _: empty, t)
        carry, _ = jax.lax.scan(
            lambda c, t: (step(whole, c, t), None), (start, zero, zero), jnp.arange(sizes.steps)
        )
    else:

        def checked(t, carry, checks):
            """The checks after `t` steps, `checks = (the last one passed, the one before)`:
            updated where the tolerance is checked. Enough units to trust a variance estimate
            (two samples, or MIN_BLOCKS_TO_STOP block means: an early step may be one block);
            QMC only at powers of two per replica (whole nets), i.e. after 1, 2, 4, ... steps
            (each a power of two of rounds)."""
            if sizes.replicas == 1:
                at_check = carry[0].count >= (2 if per_sample else MIN_BLOCKS_TO_STOP)
            else:
                at_check = (t >= 1) & ((t & (t - 1)) == 0)
            est = stream_estimate(*carry, sizes.replicas)
            met = est.stderr <= jnp.maximum(atol, rtol * jnp.abs(est.mean))
            # A variance outside its dtype's range stays there (an overflowed sum of squares
            # does not come back): no budget meets the tolerance, as at the rounding floor.
            stuck = at_rounding_floor(est.stderr, carry[0].tail) | variance_out_of_range(est)
            passed = jnp.all(met | stuck)
            return tuple(jnp.where(at_check, new, old)
                         for new, old in zip((passed, checks[0]), checks))

        def walk(state, per_step, steps):
            """Steps of `per_step` blocks from `state = (steps done, carry, checks)` until
            the tolerance is met or `steps` are done. QMC stops only when two checks in a
            row pass (nets of 2^k and 2^(k+1) points): the spread of 8 small nets that fell
            low stopped runs early and low (a 4-D camel at rtol=1e-3: 4 of 40 keys beyond 3
            sigma)."""
            run_step = sharded(per_step)
            once = sizes.replicas == 1 or QMC_PASSES_TO_STOP == 1

            def cond(state):
                t, _, (last, before) = state
                return (t < steps) & ~(last & (before | once))

            def body(state):
                t, carry, checks = state
                carry = step(run_step, carry, t)
                return t + 1, carry, checked(t + 1, carry, checks)

            return jax.lax.while_loop(cond, body, state)

        no = _carry_typed(jnp.zeros((), bool), mesh)
        state = (zero, (start, zero, zero), (no, no))
        if sizes.early_steps > 1:
            # The first step's blocks in smaller steps (the same blocks, the same points);
            # after them the whole steps go on from the second, its checks again at 2, 4,
            # ... whole steps.
            _, carry, checks = walk(state, sizes.per_step // sizes.early_steps, sizes.early_steps)
            state = (zero + 1, carry, checks)
        _, carry, _ = walk(state, sizes.per_step, sizes.steps)
    est = stream_estimate(*carry, sizes.replicas, active)
    if progress:  # (under a user's `jit`, this report closes the bar: `_progress`)
        _report(est, bar_total, mesh, last=True)
    return est


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
