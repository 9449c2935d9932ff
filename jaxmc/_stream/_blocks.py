r"""A stream's blocks: their points, and the moments of the integrand's values at them.

A loop step takes `per_step` blocks (or a device's share of them): `step_points` draws
their points (and what `step_moments` needs of them: densities, hypercubes, which blocks
count), the integrand is evaluated on all of them at once (`values`), and `step_moments`
reduces its values to the step's `Moments`. Only `values` evaluates the integrand: the
other two are compiled once per shape and serve every integrand, and a stream run step by
step outside `jit` compiles only `values` for a new integrand. Traced, the three are one
program, the same operations.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .. import _random
from .._box import to_box
from .._compiled import per_integrand
from .._fit._vegas import stratified_unit_points
from .._integrand import evaluate, ratio
from .._points._common import uint32_to_unit
from .._points._registry import unit_points
from .._points._sobol import sobol_block, sobol_scramble
from .._stats import Moments, block_moments, merge_all, tail_of
from ._sizes import extra_blocks


def replica_points(scramble, position, log2_size: int, dtype) -> jax.Array:
    """Block `position` (`2**log2_size` points on $[0,1)^d$) of the Sobol' sequence
    scrambled by `scramble = sobol_scramble(key, d)`: one QMC replica's next net block."""
    return uint32_to_unit(sobol_block(*scramble, position, log2_size), dtype, centred=True)


class Context(eqx.Module):
    """What every block of a stream reads: its key, the frozen density (a proposal, a map,
    or a VEGAS+ grid and allocation), the box, the evaluations it may make (`limit`: an
    array, so that the programs reading it serve every budget); for QMC its replicas'
    scrambles, on a fixed budget each replica's blocks in its net and beyond it, and for a
    budget given when it runs its replicas (`active`), their blocks each and the blocks in
    all."""

    key: jax.Array
    frozen: object
    lo: jax.Array
    hi: jax.Array
    limit: jax.Array
    scrambles: object = None
    active: jax.Array | None = None
    net_blocks: jax.Array | None = None
    extra: jax.Array | None = None

    @property
    def per_replica(self) -> jax.Array | None:
        """Blocks each replica walks, for a budget given when the stream runs."""
        return None if self.active is None else self.net_blocks + self.extra

    @property
    def nblocks(self) -> jax.Array | None:
        """Blocks in all, for a budget given when the stream runs."""
        return None if self.active is None else self.active * self.per_replica


def context(key, frozen, lo, hi, budget, min_replicas, *, sizes) -> Context:
    """The stream's `Context`: `budget` evaluations (`sizes.budget` where it is None), for
    `sizes.dynamic` QMC in nets that `min_replicas`, default `sizes.min_replicas`, fit in;
    both may be traced."""
    d = 1 if lo.ndim == 0 else lo.shape[0]
    scrambles = active = net_blocks = extra = None
    limit = jnp.asarray(sizes.budget if budget is None else budget, jnp.int32)
    if sizes.method == "qmc":
        scrambles = jax.vmap(lambda k: sobol_scramble(k, d))(jax.random.split(key, sizes.replicas))
    if sizes.dynamic:
        # Nets of the largest power of two of points that `min_replicas` fit in the budget,
        # as many replicas as fit, and the extra blocks the rest buys; each replica walked
        # block by block, replica after replica.
        budget = jnp.asarray(budget, jnp.int32)
        fewest = sizes.min_replicas if min_replicas is None else min_replicas
        net = jnp.left_shift(1, 31 - jax.lax.clz(budget // fewest))
        active, net_blocks = budget // net, net // sizes.block
        extra = extra_blocks(budget, active, net, sizes.block)
        limit = active * (net_blocks + extra) * sizes.block
    elif sizes.net_blocks:
        net_blocks = jnp.asarray(sizes.net_blocks, jnp.int32)
        extra = limit // (sizes.block * sizes.replicas) - net_blocks
    return Context(key, frozen, lo, hi, limit, scrambles, active, net_blocks, extra)


def block_weight(position, net_blocks, extra):
    r"""The weight of a replica's block at `position` (in blocks) in its mean, relative to a
    block of its net of `net_blocks` (a power of two), where `extra` blocks follow the net.

    The extra blocks split, by the binary digits of `extra`, into aligned runs of $2^b$
    blocks, each a net of its own (Sobol' points in aligned runs of a power of two are
    nets). The replica's mean weighs these nets $w_j \propto s_j^3$ ($s_j$ its points), each
    point by $(s_j/\mathrm{net})^2$, as their variances ask at the best rate of a scrambled
    net on a smooth integrand, $O(s^{-3})$ (Owen 1997): at that rate and below it they never
    raise the variance (weights by the count alone raise it there). The weights are fixed
    before any point is drawn, so each replica's mean stays unbiased and the replicas'
    spread its variance."""
    if net_blocks is None:
        return 1.0
    beyond = jnp.asarray(position - net_blocks, jnp.int32)
    run = jnp.left_shift(1, 31 - jax.lax.clz(jnp.maximum(beyond ^ extra.astype(jnp.int32), 1)))
    return jnp.where(beyond < 0, 1.0, (run / jnp.maximum(net_blocks, 1)) ** 2)


def replica_of(ctx: Context, b, *, sizes):
    """A QMC block's replica and its position in the replica's net."""
    if sizes.dynamic:
        return b // ctx.per_replica, b % ctx.per_replica
    return b % sizes.replicas, b // sizes.replicas


def blocks_of_step(ctx: Context, t, device, *, sizes, per_step, devices):
    """Device `device`'s blocks of step `t` (slots `[j * per_device, (j + 1) * per_device)`
    of the step's `per_step`), and whether each is one of the stream's."""
    per_device = -(-per_step // devices)
    slot = device * per_device + jnp.arange(per_device, dtype=jnp.int32)
    blocks = t * per_step + slot
    inside = (slot < per_step) & (blocks < -(-ctx.limit // sizes.block))
    return blocks, inside


def _block_points(ctx: Context, b, *, sizes):
    """Block `b`'s points (as the integrand takes them) and what its moments need of them:
    their density, or for VEGAS+ rounds their log-density and hypercubes."""
    method, lo, hi = sizes.method, ctx.lo, ctx.hi
    d = 1 if lo.ndim == 0 else lo.shape[0]
    dtype = lo.dtype
    key = jax.random.fold_in(ctx.key, b)
    if method == "adaptive":  # a VEGAS+ round on the frozen grid and allocation
        grid, counts, strata = ctx.frozen
        draw = stratified_unit_points(_random.uniform(key, (sizes.block, grid.dim), dtype),
                                      counts, strata)
        x, log_p, _ = grid.map_with_bins(draw.u)
        return (x if grid.event_ndim else x[:, 0]), (log_p, draw.cube)
    if method == "importance":  # from the frozen proposal
        return ctx.frozen.sample(key, sizes.block)
    if method == "qmc":
        r, position = replica_of(ctx, b, sizes=sizes)
        u = replica_points((ctx.scrambles[0][r], ctx.scrambles[1][r]), position,
                           sizes.block.bit_length() - 1, dtype)
        if ctx.frozen is not None:  # scrambled nets through a trained grid's map
            x, log_p = ctx.frozen.map(u)
            return (x if ctx.frozen.event_ndim else x[:, 0]), jnp.exp(log_p)
    elif method == "plain":
        u = unit_points("uniform", key, sizes.block, d, dtype=dtype)
    else:
        # Drawn in the default float dtype, then cast: this keeps the numbers of earlier
        # versions for float32 bounds under x64 (a float32 draw truncates, not rounds).
        u = unit_points("stratified", key, sizes.block, d, counts=sizes.strata).astype(dtype)
    x = to_box(u if lo.ndim else u[:, 0], lo, hi)
    return x, jnp.broadcast_to(1.0 / jnp.prod(hi - lo), (sizes.block,))


def step_points(ctx: Context, t, device, *, sizes, per_step, devices):
    """The points of device `device`'s blocks of step `t`, all of them `(blocks * block, ...)`
    as the integrand takes them, and `(blocks, inside, what their moments need)`."""
    blocks, inside = blocks_of_step(ctx, t, device, sizes=sizes, per_step=per_step,
                                    devices=devices)
    x, aux = jax.vmap(lambda b: _block_points(ctx, b, sizes=sizes))(blocks)
    return jnp.reshape(x, (-1,) + x.shape[2:]), (blocks, inside, aux)


@per_integrand
def values(x, *, f, batched):
    """The integrand at points `x` `(n, ...)`: the one program a stream run step by step
    compiles for each integrand."""
    return evaluate(f, x, batched)


def step_moments(ctx: Context, fx, points, *, sizes):
    """The step's `Moments` from the integrand's values `fx` at its points (`step_points`):
    `(moments, evaluations, non-finite values)`."""
    blocks, inside, aux = points
    fx = jnp.reshape(fx, blocks.shape + (-1,) + fx.shape[1:])
    m, evaluations, bad, values_ = jax.vmap(
        lambda b, i, f_b, a: _block_moments(ctx, b, i, f_b, a, sizes=sizes))(blocks, inside, fx, aux)
    m = merge_all(m)
    if values_ is not None:
        # One search for the largest values among all the step's blocks: a block's own
        # search and the merges of their tails cost twice as much (on a CPU).
        y, valid, f = jax.tree.map(lambda a: jnp.reshape(a, (-1,) + a.shape[2:]), values_)
        m = m._replace(tail=tail_of(y, valid, f))
    return m, jnp.sum(evaluations, dtype=jnp.int32), jnp.sum(bad, dtype=jnp.int32)


def _block_moments(ctx: Context, b, inside, fx, aux, *, sizes):
    """Block `b`'s moments from its values `fx`: `(moments, evaluations, non-finite values,
    (its values f/p, which count, and f itself through a grid's map, else None) or None)`."""
    method = sizes.method
    dtype = ctx.lo.dtype
    if method == "adaptive":
        # One VEGAS+ round: one observation, its stratified estimate v sum_h mean_h (§4.2),
        # as v sum_i y_i / n_{h(i)}; the stream's variance comes from the rounds' spread.
        log_p, cube = aux
        counts = ctx.frozen[1]
        y, bad = ratio(fx, jnp.exp(log_p))
        per_point = 1.0 / (counts.shape[0] * jnp.maximum(counts, 1).astype(y.dtype))[cube]
        mean = jnp.sum(y * jnp.reshape(per_point, (-1,) + (1,) * (y.ndim - 1)), axis=0)
        # The diagnostics are of the values y = f/p (as `stats.stratified_estimate`'s).
        m = Moments(jnp.ones((), y.dtype), mean, jnp.zeros_like(mean), tail_of(y))
        # Slots past the budget (the last step's spare ones) are dropped.
        m = jax.tree.map(lambda a: jnp.where(inside, a, jnp.zeros_like(a)), m)
        return (m, jnp.where(inside, sizes.block, 0).astype(jnp.int32),
                jnp.where(inside, jnp.sum(bad, dtype=jnp.int32), 0), None)
    y, bad = ratio(fx, aux)
    index = b * sizes.block + jnp.arange(sizes.block)
    valid = (index < ctx.limit) & inside
    m = block_moments(y, valid, with_tail=False)  # the step's tail comes from all its blocks
    if method not in ("plain", "importance"):
        # The block is one randomisation: one observation, its mean.
        unit = jnp.where(m.count > 0, 1.0, 0.0).astype(dtype)
        m = Moments(unit, m.mean, jnp.zeros_like(m.m2), m.tail)
    if method == "qmc":
        # Its replica's running mean weighs it by its points, beyond the net less
        # (`block_weight`).
        replica, position = replica_of(ctx, b, sizes=sizes)
        weight = jnp.asarray(block_weight(position, ctx.net_blocks, ctx.extra), m.count.dtype)
        m = _one_hot_moments(m._replace(count=m.count * sizes.block * weight), replica,
                             sizes.replicas)
    evaluations = jnp.sum(valid, dtype=jnp.int32)
    # Through a grid's map (bounded below) the tail test reads f's own values too.
    through_grid = fx if method == "qmc" and ctx.frozen is not None else None
    return m, evaluations, jnp.sum(bad & valid, dtype=jnp.int32), (y, valid, through_grid)


def _one_hot_moments(m: Moments, slot, slots: int) -> Moments:
    """Place a block's moments in row `slot` of `slots` rows (the others empty)."""
    hot = jnp.arange(slots) == slot
    count = jnp.where(hot, m.count, 0.0).astype(m.mean.dtype)

    def place(a):
        return jnp.where(jnp.reshape(hot, (slots,) + (1,) * a.ndim), a[None], jnp.zeros_like(a)[None])

    return Moments(count, place(m.mean), place(m.m2), m.tail)
