"""The static sizes of an `integrate` stream (`Sizes`: blocks, replicas, loop steps, the
small first steps of a tolerance run), the constants of its stopping rules, and the size of
a tolerance run's probe."""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx


BLOCK = 1 << 14  # samples per block; power of two so Sobol' blocks are (t, m, s)-nets
QMC_REPLICAS = 8  # independent scrambles of the Sobol' sequence with a tolerance (as scipy's qmc_quad)
# On a fixed budget: at least this many, and nets as large as that allows. At a QMC rate
# n^-1.5 the variance of the mean grows like replicas^2 for a given budget, so fewer, larger
# nets are more accurate; the error bar then has replicas - 1 degrees of freedom
# (`Estimate.dof`), and `Estimate.interval` is Student's t: mean +- 2 stderr alone covers
# P(|t_2| <= 2) = 0.82 with 3 replicas, the t interval of the same level 0.954. Three
# (chosen on the project's benchmarks) give the largest nets a budget allows while keeping
# an error bar. (Nets of 3 * 2^16 points, for four replicas, are no remedy: the last 2^16
# points are an unpaired net, with the larger variance of a smaller net.)
QMC_MIN_REPLICAS = 3
# With a tolerance, QMC's blocks are at most this large, and the first chunk is walked in up
# to MAX_EARLY_STEPS steps, so that its checks start at nets of 2^10 points (8 * 2^10
# evaluations), not at the chunk's nets of 2^15 (2^18 evaluations).
TOLERANCE_QMC_BLOCK = 1 << 10
MAX_EARLY_STEPS = 32
QMC_PASSES_TO_STOP = 2  # checks in a row that must pass (see `stream`)
# A tolerance is checked on block means (stratified, VEGAS+ rounds, and `_adaptive`'s
# refining rounds) from this many on: with fewer, an error bar of a few degrees of freedom
# that happened to fall low stops the run short of the tolerance (the count chosen on the
# project's benchmarks).
MIN_BLOCKS_TO_STOP = 16
# With only a tolerance (and `rtol` among it), "auto"'s pilot and "adaptive"'s training are
# first sized for this budget, not for `max_n`: about 3e4 evaluations for the pilot, 2e4 for
# the training, where `max_n`'s default sized them for 2e5 and 1.6e5.
PROBE_BUDGET = 1 << 17
# ...and sized for `max_n` after all, anew, when the probe's grid (or auto's winning
# mixture) needs more than PROBE_REACH times the probe's budget for `rtol` (variance per
# evaluation / rtol^2): a long run pays for a larger pilot (larger rounds, grids of more
# bins per axis, `adaptive_block` and `grid_bins`), which trains a better grid.
PROBE_REACH = 4
# ...for `method="adaptive"`, twice the budget: beyond it the probe's grid, refined for 32
# rounds of 2^11 points that its frozen stream then discards, cost more than training anew
# (the factor chosen on the project's benchmarks).
ADAPTIVE_PROBE_REACH = 2


class Sizes(eqx.Module):
    """Static sizes of a run."""

    method: str = eqx.field(static=True)
    block: int = eqx.field(static=True)  # samples per block
    blocks: int = eqx.field(static=True)  # blocks in the budget
    budget: int = eqx.field(static=True)  # evaluations in the budget
    per_step: int = eqx.field(static=True)  # blocks per loop step (all devices)
    steps: int = eqx.field(static=True)  # loop steps to exhaust the budget
    # With a tolerance, the first step's blocks run in `early_steps` smaller steps of
    # `per_step // early_steps` blocks, each followed by the check (1 when there are none).
    early_steps: int = eqx.field(static=True)
    strata: tuple[int, ...] = eqx.field(static=True)  # jittered-grid counts per block
    replicas: int = eqx.field(static=True)  # randomised-QMC replicas (1 otherwise)
    # Randomised QMC on a budget given when it runs (`dynamic_qmc_sizes`): `budget` is then
    # the most it may be, `replicas` the most replicas, and `min_replicas` sizes the nets.
    dynamic: bool = eqx.field(static=True, default=False)
    min_replicas: int = eqx.field(static=True, default=QMC_MIN_REPLICAS)
    # Randomised QMC on a fixed budget: blocks in each replica's net (a power of two), after
    # which it walks `extra_blocks` more (0: none, as with a tolerance; `dynamic` sizes
    # find both when they run).
    net_blocks: int = eqx.field(static=True, default=0)

    def per_block(self) -> Sizes:
        """These sizes without the budget's (`budget`, `blocks`, `steps`, `early_steps`):
        what a step's programs read, the budget coming from the stream's `Context` as an
        array. Programs compiled for them serve every budget of the same block layout, so
        a session that integrates at many budgets does not compile (and hold) one set of
        programs per budget."""
        return dataclasses.replace(self, budget=0, blocks=0, steps=0, early_steps=0)


def final_net(budget: int, min_replicas: int = QMC_MIN_REPLICAS) -> int:
    """Points per replica of randomised QMC on a fixed budget: the largest power of two
    that `min_replicas` replicas fit in (the rest of the budget buys more replicas)."""
    return 1 << int(math.floor(math.log2(max(budget // min_replicas, 1))))


def sizes(
    method: str,
    budget: int,
    chunk: int,
    devices: int,
    d: int,
    adaptive_block: int = 0,
    tolerant: bool = False,
    min_replicas: int = QMC_MIN_REPLICAS,
) -> Sizes:
    """The block size, block count and loop shape for `budget` evaluations.

    Randomised QMC with a fixed budget gives each replica the largest power of
    two of points that `min_replicas` replicas fit in (whole nets, where its
    error is smallest), spends what is left on more replicas (3 to 5 by default)
    and what those leave on extra blocks of every replica (`extra_blocks`, weighed
    by `_blocks.block_weight`); with a tolerance there are `QMC_REPLICAS` and the
    nets grow.
    """
    strata: tuple[int, ...] = ()
    replicas, net_blocks = 1, 0
    if method in ("plain", "importance"):
        # Smaller budgets get one power-of-two block, so little is masked away.
        block = min(BLOCK, 1 << max(0, math.ceil(math.log2(budget))))
        blocks = -(-budget // block)
    elif method == "qmc":
        if budget < 2 * QMC_REPLICAS:
            raise ValueError(f"`n` must be >= {2 * QMC_REPLICAS} for method 'qmc', got {budget}.")
        if tolerant:  # 8 nets grow until the tolerance or the budget stops them
            replicas = QMC_REPLICAS
            per_replica = budget // replicas
            # Small blocks, so the first checks come after nets of 2^10 points, not 2^15.
            block = min(TOLERANCE_QMC_BLOCK,
                        1 << int(math.floor(math.log2(max(per_replica // 8, 1)))))
            blocks = (per_replica // block) * replicas
        else:
            net = final_net(budget, min_replicas)  # points per replica
            replicas = budget // net
            block = extra_block(net)
            net_blocks = net // block
            blocks = (net_blocks + extra_blocks(budget, replicas, net, block)) * replicas
        budget = blocks * block
    else:
        # Block methods need several blocks for a variance: at least 8.
        if budget < 16:
            raise ValueError(f"`n` must be >= 16 for method {method!r}, got {budget}.")
        block = min(BLOCK, 1 << int(math.floor(math.log2(budget // 8))))
        if method == "adaptive":  # one VEGAS+ round per block, of the size it was trained at
            block = adaptive_block
        if method == "stratified":
            per_axis = cubic_strata(budget, block, d)
            strata = (per_axis,) * d
            block = per_axis**d
        blocks = budget // block
        budget = blocks * block
    # At least a block per device (a small chunk must not idle devices), never more blocks
    # than the budget.
    per_step = min(max(1, -(-chunk // block), devices), blocks)
    if method == "qmc":
        # Whole rounds (one block of every replica), a power of two of them per step, so
        # each replica holds a power of two of points after 1, 2, 4, ... steps.
        rounds = max(1, per_step // replicas)
        per_step = replicas * (1 << int(math.floor(math.log2(rounds))))
    steps = -(-blocks // per_step)
    early = early_steps(per_step, devices, replicas) if tolerant else 1
    return Sizes(method, block, blocks, budget, per_step, steps, early, strata, replicas,
                 net_blocks=net_blocks)


def cubic_strata(budget: int, block: int, d: int) -> int:
    """Strata per axis of a cubic stratified block of at most `block` points: the most whose whole
    blocks leave at most `1/EXTRA_GRAIN` of `budget` unspent (fewer strata, more blocks)."""
    most = int(math.floor(block ** (1.0 / d) + 1e-9))
    if most < 2:
        raise ValueError(
            f"method='stratified' needs at least 2 strata per axis in a block of "
            f"{block}, which d={d} does not allow; use method='qmc' or 'plain'.")
    for per_axis in range(most, 1, -1):
        if budget % per_axis**d <= budget // EXTRA_GRAIN:
            return per_axis
    return 2


# Randomised QMC on a fixed budget walks its nets in blocks of at most 1/EXTRA_GRAIN of a net,
# so that what whole nets leave (up to a quarter of the budget) buys extra blocks of every
# replica: the last replica-round of blocks it cannot buy is at most 1/EXTRA_GRAIN of it.
EXTRA_GRAIN = 32


def extra_block(net: int) -> int:
    """Points per block of randomised QMC with nets of `net` points on a fixed budget."""
    return max(1, min(BLOCK, net // EXTRA_GRAIN))


def extra_blocks(budget, replicas, net, block):
    """Blocks each of `replicas` replicas walks beyond its net of `net` points on `budget`
    evaluations (Python ints or arrays)."""
    return (budget - replicas * net) // (replicas * block)


def dynamic_qmc_sizes(cap: int, floor: int, chunk: int, devices: int,
                      min_replicas: int = QMC_MIN_REPLICAS) -> Sizes:
    """Randomised QMC's sizes for a budget known only when the stream runs, from `floor` to
    `cap` (one compiled program for all of them): blocks of `extra_block` of the smallest
    budget's nets, and room for every budget's replicas (fewer than `2 * min_replicas`: a
    budget holds fewer than twice `min_replicas` of its largest nets). The stream walks each
    replica's net and its extra blocks block by block, replica after replica, and skips the
    steps past its budget's blocks."""
    if floor < 2 * min_replicas or cap < floor:
        raise ValueError(f"a budget of at least {2 * min_replicas} is needed, got {floor}.")
    block = extra_block(final_net(floor, min_replicas))
    blocks = cap // block
    per_step = min(max(1, -(-chunk // block), devices), blocks)
    steps = -(-blocks // per_step)
    return Sizes("qmc", block, blocks, cap, per_step, steps, 1, (), 2 * min_replicas - 1,
                 dynamic=True, min_replicas=min_replicas)


def early_steps(per_step: int, devices: int, replicas: int) -> int:
    """Steps the first loop step's `per_step` blocks are split into with a tolerance: the
    most, up to `MAX_EARLY_STEPS`, that split them evenly with a block per device at least
    and, for QMC, a power of two of whole rounds (a block of every replica) each. A
    tolerance a few blocks meet then stops there, not after a whole chunk (2^18
    evaluations by default); later steps are whole chunks, large enough to keep an
    accelerator busy."""
    unit = max(replicas, devices)
    for steps in range(min(MAX_EARLY_STEPS, per_step), 1, -1):
        whole_rounds = replicas == 1 or steps & (steps - 1) == 0
        if per_step % steps == 0 and per_step // steps >= unit and whole_rounds:
            return steps
    return 1
