r"""The partition's adaptation rule: stratified sampling over its cells, then splitting.

MISER-like recursive stratified sampling (Press & Farrar 1990): a round puts
$n_c$ points uniformly in each leaf, estimates the integral and its variance
from the leaves' means and variances (§4.2), and halves the leaves whose
share $V_c\sigma_c$ of the Neyman-allocated error is largest.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp

from .. import _random
from .._integrand import ratio
from .._proposals._partition import MAX_LEVEL
from .._stats import slot_of_sample, stratified_estimate
from ..proposals import Partition
from ._rule import AbstractAdaptation, Integrand, Samples


# Share of a round's samples (beyond the floor of two per cell) spread evenly over the
# cells, as VEGAS+ spreads a quarter evenly over its hypercubes; the rest go in
# proportion to V_c sigma_c. Even per cell, not per volume: small cells are where
# features are, and big cells with no variance need no more than their floor.
_UNIFORM_SHARE = 0.25
# Weight, in samples, of the parent's pooled statistics a new cell starts from: a cell
# whose own samples all agree still gets a variance of about v_parent / n_c, so a
# feature its first few samples missed is not starved for good.
_PRIOR_WEIGHT = 1.0
# Share of the fitted density's mass spread in proportion to volume (defensive
# mixture), so `sample`/`pdf` keep every cell reachable.
_DEFENSIVE = 0.1


def allocate_to_cells(weight: jax.Array, volume: jax.Array, count: jax.Array, n: int, beta) -> jax.Array:
    r"""Samples per leaf slot: two each, a quarter of the rest evenly, the rest $\propto w_c^\beta$.

    `weight` is $V_c\sigma_c$ (Neyman allocation at `beta = 1`), `volume` $V_c$
    (the adaptive share's fallback when no weight is positive), `count` the
    number of leaves (slots beyond it get nothing). Systematic rounding of the
    cumulative shares, so the counts sum to `n` exactly.
    """
    slots = weight.shape[0]
    valid = jnp.arange(slots) < count
    spare = n - 2 * count
    vol = jnp.where(valid, volume, 0.0)
    w = jnp.where(valid & jnp.isfinite(weight) & (weight > 0), weight, 0.0) ** beta
    w_total = jnp.sum(w)
    adaptive = jnp.where(w_total > 0, w / jnp.where(w_total > 0, w_total, 1.0), vol)
    even = valid / jnp.maximum(count, 1).astype(vol.dtype)
    share = _UNIFORM_SHARE * even + (1 - _UNIFORM_SHARE) * adaptive
    cum = jnp.floor(jnp.cumsum(share) * spare + 0.5).astype(jnp.int32)
    # Monotone, at most `spare`, and exactly `spare` from the last leaf on: slots past
    # the leaves get no samples whatever the rounding of the float cumsum.
    cum = jnp.minimum(jax.lax.cummax(cum), spare)
    cum = jnp.where(jnp.arange(slots) >= count - 1, spare, cum)
    return jnp.where(valid, 2, 0) + jnp.diff(cum, prepend=0)


def _moments(cnt, s1, s2):
    r"""Unbiased variance and mean square of $y$ from counts and sums (0 below two samples).

    `s1` carries the components of $y$ on its last axis, `s2` is $\sum |y|^2$;
    the variance is summed over components.
    """
    c = jnp.maximum(cnt, 1.0)
    var = jnp.maximum(s2 / c - jnp.sum((s1 / c[..., None]) ** 2, axis=-1), 0.0)
    enough = cnt >= 2
    return jnp.where(enough, var * c / jnp.maximum(c - 1.0, 1.0), 0.0), jnp.where(
        enough, s2 / c, 0.0
    )


def _pool(stats, cnt, var, ms):
    """Pool a round's moments of each node into its running `(weight, variance, mean square)`.

    Nodes with fewer than two samples keep their estimates.
    """
    w = stats[:, 0]
    add = jnp.where(cnt >= 2, cnt, 0.0)
    total = jnp.where(add > 0, w + add, 1.0)
    pooled = jnp.stack(
        [w + add, (w * stats[:, 1] + add * var) / total, (w * stats[:, 2] + add * ms) / total],
        axis=-1,
    )
    return jnp.where((add > 0)[:, None], pooled, stats)


def _coarse_neighbour_score(part: Partition, score: jax.Array, log_vol: jax.Array) -> jax.Array:
    r"""Scores for leaves next to much finer scored leaves: a graded partition.

    Each scored leaf looks across the centre of each of its $2d$ faces; a
    neighbour more than four times its volume takes the leaf's score scaled to
    its own volume, $\log V_\text{nb} + \log\hat\sigma_c$. A feature that a
    coarse cell only grazes (too thinly for its samples to show) usually runs
    on through fine cells next to it, so the coarse cell is halved too.
    """
    m, d = part.corner.shape
    dtype = log_vol.dtype
    width = jnp.ldexp(jnp.ones((m, d), dtype), -part.level)
    lower = jnp.ldexp(part.corner.astype(dtype), -part.level)
    centre = lower + 0.5 * width
    eps = 2.0 ** -(MAX_LEVEL + 2)
    eye = jnp.eye(d, dtype=dtype)
    # (m, 2d, d) probe points just outside each face.
    below = centre[:, None, :] - eye[None] * (0.5 * width[:, None, :] + eps)
    above = centre[:, None, :] + eye[None] * (0.5 * width[:, None, :] + eps)
    probe = jnp.concatenate([below, above], axis=1)
    inside = jnp.all((probe >= 0) & (probe < 1), axis=-1)
    nb = part.locate(jnp.reshape(jnp.clip(probe, 0.0, 1.0 - eps), (-1, d))).reshape(m, 2 * d)
    own = jnp.broadcast_to((score - log_vol)[:, None], nb.shape)  # log sigma
    coarse = inside & jnp.isfinite(own) & (log_vol[nb] > log_vol[:, None] + math.log(4.0) - 1e-6)
    cand = jnp.where(coarse, log_vol[nb] + own, -jnp.inf)
    return jax.ops.segment_max(cand.ravel(), nb.ravel(), m)


def _split_pass(part: Partition, stats: jax.Array, u: jax.Array, y: jax.Array, node: jax.Array):
    r"""Halve the leaves with the largest $V_c \hat\sigma_c$, as many as the capacity allows.

    $\hat\sigma_c$ is the standard deviation of $y$ `(n, k)` over the round's
    samples `u` in leaf $c$ (uniform in it; `node` is each sample's leaf); a
    leaf next to much finer scored leaves is scored too
    (`_coarse_neighbour_score`). A
    leaf is halved along one of its longest edges (cells stay within 2:1, which
    keeps the cells along a curved edge few), the one whose halves differ most
    — the largest drop $\hat\sigma_c - (\hat\sigma_L + \hat\sigma_R)/2$
    where both halves hold at least two samples. The children inherit their
    parent's pooled `stats` at weight `_PRIOR_WEIGHT` (a prior their own
    samples soon outweigh); `node` follows the samples into the children.
    """
    m = part.child.shape[0]
    dtype = y.dtype
    seg = lambda a: jax.ops.segment_sum(a, node, m)  # noqa: E731
    y2 = jnp.sum(y * y, axis=-1)
    cnt, s1, s2 = seg(jnp.ones_like(y2)), seg(y), seg(y2)
    below = u < part.midpoint(node)  # (n, d)
    lb = below.astype(dtype)
    cnt_lo, s1_lo, s2_lo = seg(lb), seg(lb[:, :, None] * y[:, None, :]), seg(lb * y2[:, None])
    cnt_hi = cnt[:, None] - cnt_lo
    sd = jnp.sqrt(_moments(cnt, s1, s2)[0])
    sd_lo = jnp.sqrt(_moments(cnt_lo, s1_lo, s2_lo)[0])
    sd_hi = jnp.sqrt(_moments(cnt_hi, s1[:, None, :] - s1_lo, s2[:, None] - s2_lo)[0])

    longest = part.level == jnp.min(part.level, axis=-1, keepdims=True)
    informed = (cnt_lo >= 2) & (cnt_hi >= 2)
    drop = jnp.where(informed, sd[:, None] - 0.5 * (sd_lo + sd_hi), 0.0)
    axis = jnp.argmax(jnp.where(longest, drop, -jnp.inf), axis=-1).astype(jnp.int32)

    log_vol = part.log_unit_volume()
    is_leaf = part.is_leaf()
    score = jnp.where(
        is_leaf & (sd > 0),
        log_vol + jnp.log(jnp.where(sd > 0, sd, 1.0)),
        -jnp.inf,
    )
    score = jnp.maximum(score, _coarse_neighbour_score(part, score, log_vol))
    score = jnp.where(jnp.min(part.level, axis=-1) < MAX_LEVEL, score, -jnp.inf)
    rank = jnp.zeros((m,), jnp.int32).at[jnp.argsort(-score)].set(jnp.arange(m, dtype=jnp.int32))
    split = jnp.isfinite(score) & (rank < part.max_cells - part.n_cells)
    first = jnp.where(split, part.size + 2 * rank, m)  # first child's index; m is dropped

    onehot = jax.nn.one_hot(axis, part.dim, dtype=jnp.int32)
    corner_lo = part.corner + part.corner * onehot  # doubled along the halved axis

    def put(a, lower, upper):
        return a.at[first].set(lower, mode="drop").at[first + 1].set(upper, mode="drop")

    log_half = part.logits - math.log(2.0)
    grown = eqx.tree_at(
        lambda p: (p.child, p.axis, p.corner, p.level, p.logits, p.size),
        part,
        (
            jnp.where(split, first, part.child),
            jnp.where(split, axis, part.axis),
            put(part.corner, corner_lo, corner_lo + onehot),
            put(part.level, part.level + onehot, part.level + onehot),
            put(part.logits, log_half, log_half),
            part.size + 2 * jnp.sum(split, dtype=jnp.int32),
        ),
    )
    prior = stats.at[:, 0].set(jnp.minimum(stats[:, 0], _PRIOR_WEIGHT))
    stats = put(stats, prior, prior)
    upper = ~jnp.take_along_axis(below, axis[node][:, None], 1)[:, 0]
    node = jnp.where(split[node], first[node] + upper.astype(jnp.int32), node)
    return grown, stats, node


def _stratified_round(part: Partition, stats, raw, integrand: Integrand, beta, passes: int):
    r"""One round on `part`: the stratified estimate, the grown partition, its statistics, the samples.

    Leaf $c$ (volume $V_c$ of the box's $V$) gets $n_c$ of the `n` points
    (`allocate_to_cells` with weights $V_c\sigma_c$ from `stats`), uniform in it, so
    with $y = V f$:
    $$\hat I = \sum_c V_c \bar y_c, \qquad
      \hat V = \sum_c V_c^2 s_c^2 / n_c$$
    (stratified sampling, §4.2). Then `passes` times `_split_pass` on the same
    points grows the tree, the round's moments of each leaf are pooled into
    `stats` (weight, variance $\sigma^2$, mean square), and the masses are set to the importance optimum for the new
    cells, $P_c \propto V_c\,\text{rms}_c$, mixed with $V_c$ at weight
    `_DEFENSIVE`.
    """
    n = raw.shape[0]
    slots = part.max_cells
    ids, count = part.leaves()
    valid = jnp.arange(slots) < count
    vol = jnp.where(valid, jnp.exp(part.log_unit_volume()[ids]), 0.0)
    counts = allocate_to_cells(vol * jnp.sqrt(stats[ids, 1]), vol, count, n, beta)
    slot = slot_of_sample(counts, n)
    node = ids[slot]
    u = part.in_cells(node, raw)
    x = part.unit_to_box(u)
    x = x[:, 0] if part.event_ndim == 0 else x
    fx = integrand(x)
    log_q = -part.log_box_volume()
    y, bad = ratio(fx, jnp.exp(log_q))
    est, _ = stratified_estimate(y, slot, counts, vol, jnp.sum(bad, dtype=jnp.int32))
    weights = vol[slot] / counts.astype(y.dtype)[slot]
    samples = Samples(x, fx, jnp.broadcast_to(log_q, (n,)), weights)

    yk = jnp.reshape(y, (n, -1))
    part, stats, node = jax.lax.fori_loop(
        0, passes, lambda _, c: _split_pass(*c[:2], u, yk, c[2]), (part, stats, node)
    )
    m = part.child.shape[0]
    seg = lambda a: jax.ops.segment_sum(a, node, m)  # noqa: E731
    y2 = jnp.sum(yk * yk, axis=-1)
    cnt = seg(jnp.ones_like(y2))
    stats = _pool(stats, cnt, *_moments(cnt, seg(yk), seg(y2)))

    is_leaf = part.is_leaf()
    vol = jnp.where(is_leaf, jnp.exp(part.log_unit_volume()), 0.0)
    w = vol * jnp.sqrt(stats[:, 2])
    w_total = jnp.sum(w)
    mass = jnp.where(w_total > 0, (1 - _DEFENSIVE) * w / jnp.where(w_total > 0, w_total, 1.0), 0.0)
    mass = mass + jnp.where(w_total > 0, _DEFENSIVE, 1.0) * vol
    part = eqx.tree_at(lambda p: p.logits, part, jnp.log(jnp.where(is_leaf, mass, 1.0)))
    return est, part, stats, samples


class PartitionState(eqx.Module):
    """The partition and each node's pooled `(weight, variance, mean square)` of $f$."""

    partition: Partition
    stats: jax.Array
    n: int = eqx.field(static=True)  # points per round


class PartitionGrowth(AbstractAdaptation):
    r"""MISER-like growth of a `Partition` (Press & Farrar 1990), sampled stratified.

    Each round puts two points in every leaf, a quarter of the rest evenly and
    the rest $\propto (V_c\sigma_c)^\beta$ ($V_c$ the leaf's volume,
    $\sigma_c$ the pooled standard deviation of $f$ in it; Neyman allocation
    at $\beta = 1$); then `passes` times on the round's points, the leaves with
    the largest $V_c\sigma_c$ (and coarse leaves next to them) are halved along
    their longest edge, as many as `max_cells` allows, and the cell masses are
    set to $\propto V_c \sqrt{\overline{f^2}}$. Needs rounds of at least
    `4 * max_cells` points.
    """

    beta: float = 0.75
    passes: int = eqx.field(static=True, default=4)

    def check(self, proposal, n):
        if not isinstance(proposal, Partition):
            raise ValueError(
                f"PartitionGrowth adapts a Partition proposal, got {type(proposal).__name__}."
            )
        if n < 4 * proposal.max_cells:
            raise ValueError(
                "A Partition needs `n_per_iteration` >= 4 * max_cells (two points per cell "
                f"and as many to spare) = {4 * proposal.max_cells}, got {n}."
            )

    def init(self, key, proposal, n):
        # Each node's pooled (weight, variance, mean square); equal to start.
        stats = jnp.ones(proposal.logits.shape + (3,), proposal.lo.dtype).at[:, 0].set(0.0)
        return PartitionState(proposal, stats, n)

    def step(self, key, index, state, integrand: Integrand):
        part = state.partition
        n = state.n
        raw = _random.uniform(jax.random.fold_in(key, index), (n, part.dim), part.lo.dtype)
        est, part, stats, samples = _stratified_round(
            part, state.stats, raw, integrand, self.beta, self.passes
        )
        return PartitionState(part, stats, n), est, samples

    def proposal(self, state):
        return state.partition
