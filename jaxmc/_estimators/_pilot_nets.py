r"""The QMC pilot of `integrate(method="auto")`: scrambled Sobol' nets, measured.

`QMC_REPLICAS` scrambled Sobol' nets of a power-of-two size
(`pilot_qmc_points`, at most 1/16 of the budget), their spread giving the
variance $\sigma^2_m$ of the mean of their $m$ points, and the variance per
evaluation $v = m\,\sigma^2_m$ that `_auto` compares. QMC's $v$ keeps falling as its nets grow: the pilot measures
the rate across an eighth, a quarter, a half and the whole of its nets (the
first $2^k$ points of a net are a net), $\sigma^2 \propto m^{-1-r}$ with
$r \in [0, 2]$ fitted by least squares in log-log, and projects $v$ to the
final net size at that rate (at most `MAX_NET_GROWTH` times the pilot's size).
Measured against SciPy's nets of $2^{14}$ and $2^{17}$ points on the `auto`
benchmark's integrands (median of 4 keys), the fitted rate was within 0.6 of
the realised one on 26 of the 36 Genz cells, at most 1.0 above it (the 16-D
oscillatory at 1e5) and 1.3 below, and near 0 on the peaks QMC cannot
resolve, where the realised rate is too; the smaller of two ratios of
quarter, half and whole nets that it replaced read 0 on most and left QMC
10-300x pessimistic. The same points, each uniform, also give plain Monte
Carlo's variance: when QMC beats it by `clear_win_gain` per evaluation (15 on
nets of 512 points, 30 on 4096), the integrand is smooth at this scale, no
grid gains that much, and the grid is not trained; except, on the whole nets
(the early look's win is wider), where $f$ is a product of one-dimensional
factors (`separable`): a grid fits those exactly, and through it $f/q$ is flat
(a kink on every axis, $\exp(-\sum_j a_j|x_j - u_j|)$, won clearly on 3 of 8 keys
in 4-D, at errors 25x those of QMC through the trained grid). A pilot whose mean a
handful of points carried (effective sample size below `MIN_PILOT_ESS`:
a narrow peak; below `MIN_COMPARED_ESS` where its figure is weighed against a
trained grid's) measured nothing. Values with a power-law tail (Pareto
$\hat k > 0.2$: an unbounded integrand such as $x^{-1/2}$) keep QMC near
plain MC's variance while its replicas' spread comes out small: there QMC is
credited with plain MC's variance, never a clear win. (Bounded peaks show
such a $\hat k$ before their tail ends: Genz's 8-D corner peak 0.1-0.47 on
the pilot's points, 16 keys; but the corner singularity $(\sum x)^{-3/2}$ in
4-D, 0.17-0.68, overlaps them in $\hat k$, in QMC's gain and in how few
values carry the second moment, at $10^5$ and $10^6$ alike.)

The pilot looks first at the first quarter of its nets (`per_replica // 4`
points each): where QMC's clear win is already `EARLY_MARGIN` times the bar for
nets of that size, the other three quarters are not evaluated and go to the
stream (at a budget of 1e5: 3 nets of 2^15 instead of 5 of 2^14, 2.4-4.8x
less variance at QMC's rates); where $f$ looks `separable`, only at
`SEPARABLE_EARLY_MARGIN` times that. So too where the grid's outlook on them
(`grid_outlook`, or held out: `_held_out`) drops the grid (`outlook_drops_grid`): on the
quarter nets (4 keys of every `auto` case at 1e5, of 10 cases at 1e6) it did so only where
QMC then won. There a power-law tail, which exempts the grid from the outlook, is none
where the values reach a cap (`capped`): at 1e5 a peak's flank on a thousand values reads
as one (the oblique resonances, k-hat 0.3-1.3 on the quarter nets, below 0 on the whole
nets), and without the cap their whole nets decided, leaving the stream 5 nets of 2^14
(RMS relative error over 200 keys: 1.05e-2 -> 9.0e-3 on the 4-D resonance, as
`method="qmc"` errs there, 1.03e-2, and 1.54e-2 -> 1.38e-2 on the 12-D one; median call
2.7 -> 1.9 ms on the 4-D one).
"""
from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp

from .._box import to_box
from .._diagnostics import power_law_tail, tail_of
from .._integrand import evaluate, ratio
from .._points._sobol import sobol_scramble
from ._plan import QMC_REPLICAS
from ._stream import replica_points


PILOT_SHARE = 1 / 16  # at most this share of the budget on the QMC pilot
# QMC's pilot gain over plain MC beyond which no grid is tried, on nets of 512 points (it
# grows with them: `clear_win_gain`). Measured, 3 keys of each `auto` benchmark case: where
# QMC then won, 10-140 on nets of 512 (1e5) and 23-1e7 on 4096 (1e6); where a grid or its
# mixture did, at most 10 and 22 (power-law tails aside: they are never a clear win).
QMC_CLEAR_WIN = 15.0
# The first quarter of the pilot's nets decides a clear win alone at this multiple of
# `clear_win_gain` for its size (23.6 on nets of 128 points). Measured at 1e5, 5 keys of
# every `auto` case: 29-2700 on Genz's product peaks and Gaussians (2-16 D) and his 2-D
# families, 4-42 on his 8- and 16-D oscillatory and discontinuous ones (which decide on
# the whole nets, as before), at most 11 where a grid or its mixture won (the 8-D corner
# peak), power-law tails aside.
EARLY_MARGIN = 2.5
MIN_PILOT_ESS = 32.0  # fewer effective QMC pilot samples than this measure nothing
# ...and where QMC's figure is weighed against a trained grid's (the whole nets, and QMC's
# nets through the grid), fewer than this: 8 a replica, below which each replica's mean counts
# a handful of hits and their spread measures plain MC's variance at best (QMC gained 1.0-1.3
# over it there). A grid trained on such a sparse f is still adapting: on the 10-D ball at 1e6
# (20 keys) the whole nets read 28 effective points at the median, 32-40 on 3 keys, where QMC
# measured 909-1020 per evaluation against the trained grid's 288-786 (x 3), and on one key
# QMC won and erred 2.8%; the grid's refining rounds realise 4-6, the mixture's 4-8 (RMS error
# over the 20 keys 6.6e-3 -> 2.1e-3, the grid or the mixture on every key). No other estimate
# of the `auto` suite moved: two Gaussians on the 4-D diagonal at 1e5, vegas's 4-D Gaussian at
# 1e6 and i-flow's 8-D one, whose nets read 25-143, chose as before. The early look's verdicts
# weigh QMC against plain MC on its own points, by margins: they keep `MIN_PILOT_ESS` (the 8-D
# half-space and the 12-D resonance at 1e5 decide there on 36-45).
MIN_COMPARED_ESS = 8.0 * QMC_REPLICAS
MAX_NET_GROWTH = 32  # most the projection lets QMC's nets grow beyond the pilot's
MAX_QMC_RATE = 2.0  # scrambled nets on smooth integrands: variance n^-3 (Owen 1997), r = 2
# The pilot's points' bins on each axis (`net_values`): `grid_outlook` reads OUTLOOK_BINS of
# them, `separable` up to PILOT_BINS (`separable_bins`).
PILOT_BINS = 64
OUTLOOK_BINS = 16
# `separable`: the share of log|f|'s variance that its per-axis means explain, at least
# SEPARABLE_BINS bins per axis (more where the points allow, `separable_bins`), and the floor,
# relative to the largest |f|, that keeps zeros finite.
SEPARABLE_SHARE = 0.95
SEPARABLE_BINS = 16
SEPARABLE_CHANCE = 0.1  # most of the share that finer bins may explain by chance
SEPARABLE_FLOOR = 1e-3
SEPARABLE_POINTS = 512  # per replica at most (the first of them, a net)
OUTLOOK_FLOOR = 1e-3  # `grid_outlook`'s least density on a bin, relative to the mean
# A grid whose outlook on QMC's values (`grid_outlook`, times the grid's cost per evaluation)
# costs this many times QMC is not even screened (`outlook_drops_grid`). Measured at 1e5 and
# 1e6, 3 keys of every `auto` case whose values neither had a power-law tail nor looked like a
# product (the screen's exemptions): the outlook cost 0.8-330x QMC where QMC then won (4-D
# camel, annulus, oblique resonances, 3-D ball, 8-D half-space; the young grid 1.8-70x), and
# read 0 (in-sample the grid fits the few points that hit) on the 10-D ball, where the grid
# won; on two Gaussians on the 4-D diagonal, 0.8-5x at 1e6, where the mixture seeded from the
# grid won (hence `outlook_drops_grid`'s bound on QMC's cost). The outlook has no
# stratification, which the young grid has (the annulus: 0.64 against its 0.14): hence twice
# the screen's margin.
OUTLOOK_MARGIN = 4.0
# ...and there the early look's clear win must be this many times its bar (5 lies between
# 1.2-2.2, measured where QMC won early on Genz's 8- and 16-D continuous and 8-D corner
# peak at 1e6 and erred 10-60x as much as QMC through the grid, and 12-7700 on his product
# peaks, Gaussians and 2-D corner peak, where QMC does as well; 10 keys at 1e5 and 1e6).
SEPARABLE_EARLY_MARGIN = 5.0
# A grid whose outlook gains less than this over plain MC on QMC's points is not screened
# either where it costs more than QMC at all (`outlook_drops_grid`): flattering as the
# outlook is, f concentrates on no axis, and no mixture seeded from the grid has won there.
# Measured at 1e5 and 1e6 (4 keys of every `auto` case): the outlook's gain 1.3-3.1 on the
# oblique resonances, the annulus, the 3-D ball and i-flow's 4-D camel, where QMC won on
# every key (at 1e5 the young grid was screened on 12 of their 20 runs, at 1.2-68x QMC's
# cost; at 1e6 the 4-D resonance trained it in full on 4 keys of 10); 11-16 on two Gaussians
# on the 4-D diagonal, where the mixture won; 13-17 on the 8-D half-space (QMC won; on 1 key
# of 24, QMC through the trained grid).
OUTLOOK_FLAT_GAIN = 4.0
# On the early look, values whose largest is within this factor of their `CAPPED_RANK`-th
# largest have reached their cap (`capped`): a power-law tail read there is a bounded peak's
# flank, which the outlook's exemption for such tails (`outlook_drops_grid`) need not spare.
# Measured on the quarter nets at 1e5 (1024 values, 10 keys of every `auto` case): 1.06-1.38
# on the 4-D oblique resonance and 1.11-2.14 on the 12-D one, whose k-hat there (0.3-1.3)
# falls below 0 on the whole nets (4096 values), and 1.52-2.14 on i-flow's 4-D camel (QMC won
# on all three); 2.2-13 on x^-1/3 in 6-D, 1.8-7.3 on (sum x)^-3/2 in 4-D, 2.1-10.5 on x^-1/2
# in 2-D, where the grid wins. With the exemption lifted altogether, the early look dropped the
# grid on 9 and 10 of the resonances' keys and 4 of the camel's, and on one of x^-1/3's (its
# ratio 10.6, which the cap keeps exempt).
EARLY_CAP_RATIO = 2.5
CAPPED_RANK = 10


def pilot_qmc_points(budget: int) -> int:
    """Points per replica of the QMC pilot: a power of two, 64 to 4096, within `PILOT_SHARE`."""
    share = max(budget * PILOT_SHARE / QMC_REPLICAS, 1)
    return min(max(1 << int(math.floor(math.log2(share))), 64), 4096)


def clear_win_gain(per_replica: int) -> float:
    """`QMC_CLEAR_WIN` for nets of `per_replica` points: as the cube root of their size (the
    gain of QMC over plain MC grows with its nets, 2-8x from 512 to 4096 points where QMC
    won, 1.5-3x where a grid did)."""
    return QMC_CLEAR_WIN * (per_replica / 512) ** (1 / 3)


def relative_variance(mean, variance) -> jax.Array:
    """Variance scaled by the squared mean (summed over components); scale-free."""
    mean2 = jnp.maximum(mean**2, jnp.finfo(mean.dtype).tiny)
    return jnp.sum(jnp.where(mean != 0, variance / mean2, variance))


class QMCFigures(eqx.Module):
    """What the QMC pilot's nets measured."""

    variance: jax.Array  # projected variance per evaluation (relative)
    clear_win: jax.Array  # QMC beats plain MC on its points by `clear_win_gain`
    blind: jax.Array  # saw nothing, or too few effective points to measure anything
    heavy: jax.Array  # the values have a power-law tail (Pareto k-hat > 0.2)
    plain: jax.Array  # plain MC's relative variance per evaluation, on the same points
    # f looks like a product of one-dimensional factors (`separable`; QMC's pilot only)
    separable: jax.Array = eqx.field(default_factory=lambda: jnp.asarray(False))
    # the relative variance per evaluation of a product density fitted in-sample to the
    # nets' values (`grid_outlook`; the whole nets only, 0 where unread)
    grid_outlook: jax.Array = eqx.field(default_factory=lambda: jnp.asarray(0.0))
    # the values' tail reaches a cap (`capped`; the early look only, False where unread)
    capped: jax.Array = eqx.field(default_factory=lambda: jnp.asarray(False))


def _net_units(key, d, dtype, first, blocks, log2_block):
    """Points `(QMC_REPLICAS, blocks * 2**log2_block, d)` on $[0,1)^d$: blocks `first`, ...,
    `first + blocks - 1` of `2**log2_block` points of the pilot's scrambled Sobol' nets (one
    scramble per replica, from `key`)."""

    def replica(k):
        scramble = sobol_scramble(k, d)
        return jnp.concatenate([replica_points(scramble, first + b, log2_block, dtype)
                                for b in range(blocks)])

    return jax.vmap(replica)(jax.random.split(key, QMC_REPLICAS))


def _axis_bins(bins, count) -> jax.Array:
    """Each point's bin on each axis, of `count` bins per axis (a power of two up to
    `PILOT_BINS`), as one flat index into `d * count` (axis-major): `(n, d)`, from the
    pilot's `bins` `(..., d)` (`net_values`)."""
    d = bins.shape[-1]
    coarse = bins.astype(jnp.int32) // (PILOT_BINS // count)
    return jnp.reshape(coarse, (-1, d)) + count * jnp.arange(d, dtype=jnp.int32)


def _axis_bin_sums(index, w, count) -> jax.Array:
    """Sums of the per-point `w` `(n,)` over every axis's `count` bins (`_axis_bins`): one
    scatter-add, `(d * count,)`."""
    return jnp.zeros((index.shape[1] * count,), w.dtype).at[index].add(w[:, None])


def separable_bins(n: int, d: int) -> int:
    """Bins per axis for `separable` on `n` points in `d` dimensions: the most, a power of two
    from `SEPARABLE_BINS` to `PILOT_BINS`, whose chance share $d(B-1)/n$ is at most
    `SEPARABLE_CHANCE` (`SEPARABLE_BINS` where none is)."""
    count = PILOT_BINS
    while count > SEPARABLE_BINS and d * (count - 1) > SEPARABLE_CHANCE * n:
        count //= 2
    return count


def separable(bins, y) -> jax.Array:
    r"""Whether $f$ looks like a product of one-dimensional factors $\prod_j g_j(x_j)$, from
    its values `y` `(QMC_REPLICAS, m, ...)` on the pilot's nets, whose points lie in `bins`
    `(QMC_REPLICAS, m, d)` (`net_values`): the per-axis means of
    $z = \log(|f| + 10^{-3}\max|f|)$ in $B$ bins per axis (the main effects of $z$;
    every bin holds $n/B$ of a net's $n$ points; `separable_bins`) explain at least
    `SEPARABLE_SHARE` of $z$'s variance,
    $$\frac{B}{n^2}\sum_{j,b} S_{jb}^2 \Big/ \frac1n \sum_i z_i^2 \ge s,$$
    $S_{jb}$ the sum of the centred $z$ over bin $b$ of axis $j$, adjusted for the share
    $c = d(B-1)/n$ that bins explain by chance, $(\text{share} - c)/(1 - c)$. A VEGAS grid
    is a product of axis densities: on such an $f$ it converges to $q \propto |f|$ and $f/q$
    is flat. Measured on 8 nets of 512 points (128), 6 keys, at 16 bins: 0.98-1.02
    (0.98-1.25: the main effects overlap in-sample) on Genz's product peaks, Gaussians,
    corner peaks and 8- and 16-D continuous family; 0.93 on his 2-D continuous one (kinks
    steeper than the bins), 0.91-0.97 on $x^{-1/3}$, $x^{-1/2}$ and $(\sum x)^{-3/2}$,
    0.57-0.63 on his discontinuous family and the 3-D ball, at most 0.52 on the rest of the
    `auto` suite. A singular factor's logarithm varies in its first bin as much as across
    the rest ($\log x$ on $[0, 1/B]$ has variance 1, as on $[0, 1]$), which leaves $1/B$ of
    its variance unexplained: hence finer bins where the points allow. At 64 bins (8 nets
    of 512 points, 12 keys) $x^{-1/3}$ in 6-D read 1.00-1.02 and $x^{-1/2}$ in 2-D
    0.96-0.98 (before, 0.91-0.93 and 0.89-0.93: on 2 keys of 16 at 1e6 the grid's outlook
    on QMC's nets then dropped the grid for $x^{-1/3}$, their $\hat k$ at 0.19, and QMC erred
    6-12x the grid), $(\sum x)^{-3/2}$ in 4-D 0.94-0.95; no other verdict in the suite moved
    (12 keys, at 1e5 and 1e6). Never in one dimension, where every $f$ is one factor."""
    d, m = bins.shape[-1], min(y.shape[1], SEPARABLE_POINTS)  # a net's first points: a net
    if d == 1:
        return jnp.asarray(False)
    count = separable_bins(y.shape[0] * m, d)
    index = _axis_bins(bins[:, :m], count)
    a = jnp.abs(jnp.reshape(y[:, :m], (index.shape[0], -1)))
    a = jnp.sqrt(jnp.sum(a**2, axis=1))  # in quadrature over an array-valued f's components
    z = jnp.log(a + SEPARABLE_FLOOR * jnp.max(a) + jnp.finfo(a.dtype).tiny)
    centre = jnp.mean(z)
    z = z - centre
    # The main effects' share of the variance (the first-order Sobol' indices of z, summed),
    # from the bins' sums.
    sums = _axis_bin_sums(index, z, count)
    n = z.shape[0]
    variance = jnp.sum(z**2) / n
    # (A constant f, zero or not, has no factors to read: z's spread is then rounding.)
    varies = variance > (jnp.finfo(z.dtype).eps * (1 + jnp.abs(centre))) ** 2 * 1e6
    share = count * jnp.sum(sums**2) / n**2 / jnp.where(varies, variance, 1.0)
    # In-sample, bins alone explain d (bins - 1) / n of what no axis explains: adjusted, as R^2.
    chance = d * (count - 1) / n
    return varies & ((share - chance) / (1 - chance) >= SEPARABLE_SHARE)


def net_points(key, lo, hi, first, blocks, log2_block):
    """`_net_units` in the box `(QMC_REPLICAS, m, d)` (or without `d` in one dimension)."""
    d = 1 if lo.ndim == 0 else lo.shape[0]
    return _in_box(_net_units(key, d, lo.dtype, first, blocks, log2_block), lo, hi)


def _in_box(u, lo, hi):
    return jax.vmap(lambda ur: to_box(ur if lo.ndim else ur[:, 0], lo, hi))(u)


@eqx.filter_jit
def net_values(key, lo, hi, f, batched, first, blocks, log2_block, with_bins=False):
    """Integrand values `(QMC_REPLICAS, blocks * 2**log2_block, ...)` at `net_points`; with
    `with_bins`, also each point's `PILOT_BINS` bin on each axis `(..., d)` (int8), for
    `separable` and `grid_outlook` (made here, from the points at hand, rather than anew in
    their programs)."""
    d = 1 if lo.ndim == 0 else lo.shape[0]
    u = _net_units(key, d, lo.dtype, first, blocks, log2_block)
    volume = jnp.prod(hi - lo)
    y = jax.vmap(lambda xr: ratio(evaluate(f, xr, batched), 1 / volume)[0])(_in_box(u, lo, hi))
    if not with_bins:
        return y
    bins = jnp.clip(jnp.floor(u * PILOT_BINS), 0, PILOT_BINS - 1).astype(jnp.int8)
    return y, bins


@eqx.filter_jit
def grid_net_values(key, grid, f, batched, log2_size):
    r"""The values $f/q$ `(QMC_REPLICAS, 2**log2_size, ...)` of whole scrambled Sobol' nets
    carried through a VEGAS `grid`'s map ($x = G(u)$, $q$ the grid's density)."""
    u = _net_units(key, grid.dim, grid.lo.dtype, 0, 1, log2_size)

    def replica(ur):
        x, log_q = grid.map(ur)
        return ratio(evaluate(f, x if grid.event_ndim else x[:, 0], batched), jnp.exp(log_q))[0]

    return jax.vmap(replica)(u)


def outlook_values(bins, y) -> tuple[jax.Array, jax.Array, jax.Array]:
    """`(each point's bins, values, squared moduli)` of `y` `(R, m, ...)` for an outlook: flat,
    `OUTLOOK_BINS` per axis, in units of the largest value (squares may overflow float32)."""
    index = _axis_bins(bins, OUTLOOK_BINS)
    values = jnp.reshape(y, (index.shape[0], -1))
    scale = jnp.max(jnp.abs(values))
    values = values / jnp.where(scale > 0, scale, 1)
    return index, values, jnp.sum(values**2, axis=1)


def product_log_density(index, square) -> jax.Array:
    r"""$\log q_j(b)$, $q_j(b) \propto \sqrt{\overline{f^2}_{jb}}$: mean 1, `OUTLOOK_FLOOR` least"""
    d = index.shape[1]
    sums = _axis_bin_sums(index, square, OUTLOOK_BINS)
    counts = _axis_bin_sums(index, jnp.ones_like(square), OUTLOOK_BINS)
    rms = jnp.reshape(jnp.sqrt(sums / jnp.maximum(counts, 1)), (d, OUTLOOK_BINS))
    mean = jnp.maximum(jnp.mean(rms, axis=1, keepdims=True), jnp.finfo(square.dtype).tiny)
    return jnp.log(jnp.reshape(jnp.maximum(rms / mean, OUTLOOK_FLOOR), (-1,)))


def outlook_read(log_q, index, values, square) -> jax.Array:
    r"""The density `log_q`'s relative variance per evaluation read on points (`outlook_values`),
    $\overline{|f|^2/\prod_j q_j} / \bar f^2 - 1$ (`inf` if all are 0); $f = 0$ adds 0 even where
    $1/\prod_j q_j$ overflows (the floor on 13 of 16 axes in float32), never NaN."""
    weight = jnp.exp(-jnp.sum(log_q[index], axis=1))
    second = jnp.mean(jnp.where(square > 0, square * weight, 0.0))
    mean_square = jnp.sum(jnp.mean(values, axis=0) ** 2)
    ratio = second / jnp.maximum(mean_square, jnp.finfo(square.dtype).tiny)
    return jnp.where(mean_square > 0, ratio - 1, jnp.inf)


def grid_outlook(bins, y) -> jax.Array:
    r"""What importance sampling from a product of per-axis densities could do for $f$, as
    read on its values `y` `(QMC_REPLICAS, m, ...)` on the pilot's nets, in `bins` (`net_values`):
    VEGAS's density fitted to them (`product_log_density`) and its relative variance per
    evaluation on the same points (`outlook_read`, at least 0; summed over an array-valued
    $f$'s components). Fitted and read on the same points, it flatters the density, most where
    the nets saw a peak through few points (`_held_out` reads it on points it was not fitted
    to). 0 (no outlook) in one dimension, where a grid is any piecewise-constant density."""
    if bins.shape[-1] == 1:
        return jnp.zeros((), y.dtype)
    index, values, square = outlook_values(bins, y)
    return jnp.maximum(outlook_read(product_log_density(index, square), index, values, square), 0)


def outlook_drops_grid(qmc: QMCFigures, grid_cost: float, seeded_best: float) -> jax.Array:
    """Whether the grid is dropped before it is trained at all: its outlook (`grid_outlook`,
    which flatters it) at `grid_cost` per evaluation relative to QMC costs `OUTLOOK_MARGIN`
    times QMC, whose values neither miss the integrand, nor have a power-law tail, nor look
    like a product (the exemptions of `auto`'s screen of the young grid), and whose cost is
    below `seeded_best`, the least a density seeded from the grid has cost (a mixture of
    Gaussians, which the outlook cannot foresee: on two Gaussians on the 4-D diagonal at 1e6
    the outlook cost 0.8-5x QMC, then the mixture won, QMC at 4.8-30); or costs more than
    QMC where it gains less than `OUTLOOK_FLAT_GAIN` over plain MC. A power-law tail whose
    values reach a cap (`QMCFigures.capped`) is no exemption: a bounded peak's flank."""
    outlook = grid_cost * qmc.grid_outlook
    costlier = outlook > OUTLOOK_MARGIN * qmc.variance
    cheap = qmc.variance < seeded_best
    flat = OUTLOOK_FLAT_GAIN * qmc.grid_outlook >= qmc.plain
    dropped = (costlier & cheap) | (flat & (outlook > qmc.variance))
    return dropped & ~qmc.blind & ~(qmc.heavy & ~qmc.capped) & ~qmc.separable


def capped(y) -> jax.Array:
    r"""Whether the values `y` `(QMC_REPLICAS, m, ...)` reach a cap: for every component, the
    largest $|y|$ is at most `EARLY_CAP_RATIO` times the `CAPPED_RANK`-th largest (not 0).

    A bounded peak sampled too thinly shows the flank of its peak as a power-law tail (a
    Lorentzian across the cube: $P(f > t) \propto t^{-1/2}$ up to its height, $\hat k$ near
    1 on a thousand values), but its largest values crowd under the height; a singularity's go
    on growing (for a tail of shape $k$ the largest is about $10^k$ times the tenth largest:
    3.2 at $k = 1/2$). The two overlap for $k$ below about 0.4, so this reads the early look
    alone, where a wrong call costs efficiency (QMC is unbiased, its error bar bounded), and
    the whole nets, four times as many values, judge the tail without it."""
    top = tail_of(jnp.reshape(y, (-1,) + y.shape[2:])).top  # (..., TAIL + 1), decreasing
    largest, ranked = top[..., 0], top[..., CAPPED_RANK - 1]
    return jnp.all((ranked > 0) & (largest <= EARLY_CAP_RATIO * ranked))


def measure_nets(y, growth, bar, tail_gain=math.inf, min_ess=MIN_COMPARED_ESS):
    """QMC's figures from its replicas' values `y` `(QMC_REPLICAS, m, ...)`: `QMCFigures`,
    a clear win where plain MC's variance per evaluation on the same points is `bar`
    times QMC's; no power-law tail where it is `tail_gain` times QMC's (see
    `_pilot_grid.GRID_QMC_TAIL_GAIN`); blind below `min_ess` effective points."""
    per_replica = y.shape[1]

    def relative_variance_per_evaluation(values):
        means = jnp.mean(values, axis=1)
        variance = jnp.var(means, axis=0, ddof=1) / QMC_REPLICAS
        return relative_variance(jnp.mean(means, axis=0), variance) * values.shape[0] * values.shape[1]

    # The first half (quarter, eighth) of a net is a net: its variance at four sizes.
    sizes = [per_replica >> k for k in (3, 2, 1, 0)]
    by_size = jnp.stack([relative_variance_per_evaluation(y[:, :m]) for m in sizes])
    full = by_size[-1]
    flat = jnp.reshape(y, (-1,) + y.shape[2:])
    mean = jnp.mean(flat, axis=0)
    plain = relative_variance(mean, jnp.var(flat, axis=0, ddof=1))
    # Effective sample size (sum |y|)^2 / sum y^2: ~1 when a single point hit a peak.
    tiny = jnp.finfo(flat.dtype).tiny
    ess = jnp.min(jnp.sum(jnp.abs(flat), axis=0) ** 2 / jnp.maximum(jnp.sum(flat**2, axis=0), tiny))
    measured = ess >= min_ess
    # QMC's variance per evaluation keeps falling as its nets grow, at the rate the pilot
    # shows across its four sizes (least squares in log-log: each size's figure is an
    # 8-replica variance, noisy): n^-(1+r) per replica, r in [0, MAX_QMC_RATE], 0 being
    # plain MC's rate.
    doublings = jnp.arange(len(sizes), dtype=full.dtype) - (len(sizes) - 1) / 2  # centred log2(m)
    rate = -jnp.sum(doublings * jnp.log2(by_size)) / jnp.sum(doublings**2)
    rate = jnp.clip(jnp.where(jnp.isfinite(rate), rate, 0.0), 0.0, MAX_QMC_RATE)
    projected = full * jnp.asarray(growth, full.dtype) ** -rate
    # An unbounded integrand (a power-law tail of the values, k-hat > 0.2) keeps QMC's
    # variance near plain MC's and makes the replicas' spread skewed and small (the bound of
    # `bounded_variance`): QMC is credited with plain MC's variance there, and no clear win.
    heavy = jnp.any(power_law_tail(tail_of(flat))) & ~(plain >= tail_gain * full)
    projected = jnp.where(heavy, jnp.maximum(projected, plain), projected)
    blind = jnp.all(mean == 0) | ~measured
    clear_win = (plain >= bar * full) & measured & ~heavy
    return QMCFigures(projected, clear_win, blind, heavy, plain)


def early_look_figures(bins, y, growth, bar) -> QMCFigures:
    """`measure_nets` of the early look's nets `y`, whose clear win must be
    `SEPARABLE_EARLY_MARGIN` times `bar` where $f$ looks `separable`; their `grid_outlook`,
    and whether their values reach a cap (`capped`)."""
    product = separable(bins, y)
    qmc = measure_nets(y, growth, jnp.where(product, SEPARABLE_EARLY_MARGIN, 1.0) * bar,
                       min_ess=MIN_PILOT_ESS)
    return eqx.tree_at(lambda q: (q.separable, q.grid_outlook, q.capped), qmc,
                       (product, grid_outlook(bins, y), capped(y)))


def whole_nets_figures(bins, y, early_stop, growth, bar) -> QMCFigures:
    """`measure_nets` of the whole nets `y`: their clear win only where $f$ does not look
    `separable` (a grid fits a product of one-dimensional factors exactly), or where the early
    look chose QMC (`early_stop`: its clear win, or a grid its outlook dropped); and their
    `grid_outlook`."""
    qmc = measure_nets(y, growth, bar)
    product = separable(bins, y)
    win = (qmc.clear_win & ~product) | early_stop
    return eqx.tree_at(lambda q: (q.clear_win, q.separable, q.grid_outlook), qmc,
                       (win, product, grid_outlook(bins, y)))
