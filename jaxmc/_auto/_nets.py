r"""Randomised QMC's pilot: scrambled Sobol' nets, their values, and what they measure.

$R$ scrambled Sobol' nets of $m$ points (a power of two) give QMC's variance per evaluation
at nets of $m$ points from the spread of their means. QMC's variance per evaluation keeps
falling as its nets grow: the first $2^k$ points of a net are a net, so the same replicas
measure it at $m/8$, $m/4$, $m/2$ and $m$ points, $\sigma^2 \propto m^{-1-r}$ with $r \in
[0, 2]$ fitted by least squares in log-log (2 is scrambled nets' rate on smooth
integrands, Owen 1997), and the figure is projected to the stream's net size at that rate
(at most `MAX_NET_GROWTH` times the pilot's). Each point is uniform, so the same values also
give plain Monte Carlo's variance, and the outlook of a density fitted to them
(`product_outlook`).
"""

from __future__ import annotations

import math
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._box import to_box
from .._diagnostics import power_law_tail, tail_of
from .._integrand import ratio
from .._points._sobol import sobol_scramble
from .._stream._blocks import replica_points, values
from ._figures import Figure, blind, iid_figure, relative_variance


REPLICAS = 8  # scrambled nets in the pilot (as SciPy's `qmc_quad`): 7 degrees of freedom
MAX_NET_GROWTH = 32  # most the projection lets QMC's nets grow beyond the pilot's
MAX_QMC_RATE = 2.0  # scrambled nets on smooth integrands: variance n^-3 (Owen 1997)
# The pilot's points' bins on each axis, in which the product outlook fits its density.
OUTLOOK_BINS = 16
OUTLOOK_FLOOR = 1e-3  # the outlook density's least value on a bin, relative to its mean


class NetFigures(eqx.Module):
    """What QMC's pilot nets measured (all scalars)."""

    qmc: Figure  # QMC's, projected to the stream's nets
    plain: Figure  # plain Monte Carlo's on the same points
    heavy: jax.Array  # the values may have a power-law tail (Pareto k-hat > 1/4)
    blind: jax.Array  # they saw nothing, or too few effective points
    outlook: Figure  # a product density's, fitted and read on halves of the nets


def _net_units(key, d, dtype, first, blocks, log2_block):
    """Points `(REPLICAS, blocks * 2**log2_block, d)` on $[0,1)^d$: blocks `first`, ...,
    `first + blocks - 1` of the pilot's scrambled Sobol' nets (one scramble per replica)."""

    def replica(k):
        scramble = sobol_scramble(k, d)
        return jnp.concatenate([replica_points(scramble, first + b, log2_block, dtype)
                                for b in range(blocks)])

    return jax.vmap(replica)(jax.random.split(key, REPLICAS))


def _bins(u):
    """Each point's `OUTLOOK_BINS` bin on each axis (int8)."""
    return jnp.clip(jnp.floor(u * OUTLOOK_BINS), 0, OUTLOOK_BINS - 1).astype(jnp.int8)


def net_values(key, lo, hi, f, batched, first, blocks, log2_block):
    """Integrand values $f/p$ `(REPLICAS, blocks * 2**log2_block, ...)` on the pilot's nets
    (`_net_units` in the box), and each point's bin on each axis `(..., d)`. Only the values
    are compiled for each integrand (`values`); the points once per shape."""
    x, p, bins = _net_points(key, lo, hi, first=first, blocks=blocks, log2_block=log2_block)
    return _per_replica(values(x, f=f, batched=batched), p), bins


@partial(jax.jit, static_argnames=("first", "blocks", "log2_block"))
def _net_points(key, lo, hi, *, first, blocks, log2_block):
    """The points of `net_values`, flat `(REPLICAS * m, ...)`, their density and bins."""
    d = 1 if lo.ndim == 0 else lo.shape[0]
    u = _net_units(key, d, lo.dtype, first, blocks, log2_block)
    x = to_box(jnp.reshape(u, (-1, d)) if lo.ndim else jnp.reshape(u, (-1,)), lo, hi)
    p = jnp.broadcast_to(1 / jnp.prod(hi - lo), x.shape[:1])
    return x, p, _bins(u)


@jax.jit
def _per_replica(fx, p):
    """The values $f/p$ `(REPLICAS, m, ...)` (non-finite ones zeroed, as `ratio` does)."""
    y = ratio(fx, p)[0]
    return jnp.reshape(y, (REPLICAS, -1) + y.shape[1:])


def mapped_net_values(key, density, f, batched, log2_size):
    r"""The values $f/q$ `(REPLICAS, 2**log2_size, ...)` of whole nets carried through a
    map `density` (a trained grid's: $x = G(u)$, $q$ its density), and $f$ there (flat)."""
    x, q = _mapped_points(key, density, log2_size=log2_size)
    fx = values(x, f=f, batched=batched)
    return _per_replica(fx, q), fx


@partial(jax.jit, static_argnames="log2_size")
def _mapped_points(key, density, *, log2_size):
    u = _net_units(key, density.dim, density.lo.dtype, 0, 1, log2_size)
    x, log_q = density.map(jnp.reshape(u, (-1, density.dim)))
    return (x if density.event_ndim else x[:, 0]), jnp.exp(log_q)


def _replica_figures(y, growths):
    """The logarithm of QMC's relative variance per evaluation from the means of replicas `y`
    `(R, m, ...)`, projected `growths`-fold beyond nets of `m` points (one per growth) at the
    rate fitted across nets of `m/8 .. m` points."""
    replicas, per_replica = y.shape[:2]
    sizes = [per_replica >> k for k in (3, 2, 1, 0)]

    def at(m):
        means = jnp.mean(y[:, :m], axis=1)
        variance = jnp.var(means, axis=0, ddof=1) / replicas
        return relative_variance(jnp.mean(means, axis=0), variance) * replicas * m

    by_size = jnp.log2(jnp.stack([at(m) for m in sizes]))
    doublings = jnp.arange(len(sizes), dtype=by_size.dtype) - (len(sizes) - 1) / 2
    rate = -jnp.sum(doublings * by_size) / jnp.sum(doublings**2)
    rate = jnp.clip(jnp.where(jnp.isfinite(rate), rate, 0.0), 0.0, MAX_QMC_RATE)
    return by_size[-1] * math.log(2) - rate * jnp.log(jnp.asarray(growths, by_size.dtype))


def qmc_figure(y, growths) -> Figure:
    r"""QMC's figure from replicas `y` `(R, m, ...)`, projected `growths`-fold (a number, or a
    tuple: then one figure per growth, stacked): its logarithm's standard deviation by the
    jackknife over the replicas, $\sqrt{\frac{R-1}{R}\sum_i(\theta_{(i)} - \bar\theta)^2}$
    (each $\theta_{(i)}$ the whole projected figure without replica $i$)."""
    replicas = y.shape[0]
    log_v = _replica_figures(y, growths)
    others = np.array([[j for j in range(replicas) if j != i] for i in range(replicas)])
    leave_one_out = jax.vmap(lambda rows: _replica_figures(y[rows], growths))(others)
    centred = leave_one_out - jnp.mean(leave_one_out, axis=0)
    spread = jnp.sum(centred**2, axis=0) * (replicas - 1) / replicas
    finite = jnp.isfinite(log_v) & jnp.all(jnp.isfinite(leave_one_out), axis=0)
    return Figure(jnp.where(finite, jnp.exp(log_v), jnp.inf),
                  jnp.where(finite, jnp.sqrt(spread), jnp.inf))


def nets_figures(y, bins, growth) -> NetFigures:
    """`NetFigures` of the pilot's values `y` `(R, m, ...)` in `bins` (`net_values`), QMC's
    projected `growth`-fold (a tuple: stacked, one per growth) and credited as its stream
    would report it (`credited_figures`)."""
    qmc, plain, suspected = credited_figures(y, growth)
    flat = jnp.reshape(y, (-1,) + y.shape[2:])
    return NetFigures(qmc, plain, suspected, blind(flat, y.shape[0]), product_outlook(bins, y))


def credited_figures(y, growth, fx=None) -> tuple[Figure, Figure, jax.Array]:
    """QMC's figure from replicas `y` `(R, m, ...)` projected `growth`-fold (`qmc_figure`),
    plain MC's on the same values (`iid_figure`) and whether their tail may be a power law:
    `(qmc, plain, suspected)`. Where the stream would report plain MC's variance, the i.i.d.
    bound, QMC is credited with it: where the values' tail passes the stream's own test
    (`power_law_tail`, as `bounded_variance` applies it; given `fx`, the integrand's values
    there, flat, as a stream through a grid's map gives them)."""
    flat = jnp.reshape(y, (-1,) + y.shape[2:])
    tail = tail_of(flat, f=None if fx is None else jnp.reshape(fx, flat.shape))
    plain, suspected = iid_figure(flat, tail=tail)
    heavy = jnp.any(power_law_tail(tail))
    qmc = qmc_figure(y, growth)
    value = jnp.where(heavy, jnp.maximum(qmc.value, plain.value), qmc.value)
    return Figure(value, jnp.where(heavy, jnp.inf, qmc.log_sd)), plain, suspected


def product_outlook(bins, y) -> Figure:
    r"""What importance sampling from a product of per-axis densities could do for $f$.

    VEGAS's grid converges to a product density $q(x) = \prod_j q_j(x_j)$; the outlook fits
    one to the pilot's values on $B$ bins per axis, two ways: $q_j(b) \propto \exp\bar z_{jb}$
    with $\bar z_{jb}$ the mean of $z = \log|f|$ over bin $b$ of axis $j$ (a product
    $\prod_j g_j(x_j)$ is fitted up to the bins' resolution whatever its range; a zero of
    $f$ reads as the least $|f|$ seen), and VEGAS's own $q_j(b) \propto (\overline{f^2}_{jb})^{1/2}$
    (which an indicator needs). Each is fitted to the values of half of the replicas and its
    relative variance per evaluation, $\overline{|f|^2/q} / \bar f^2 - 1$, read on the other
    half, both ways: held out, as read on the points it was fitted to it flatters a sparse
    $f$ without bound. Of $B$ = 2, 4, 8, 16 and the two fits, the least is kept (chosen by
    cross-validation: few points in many dimensions fit few bins), with its logarithm's
    standard deviation from that of the mean of $|f|^2/q$ it read. 0 in one dimension,
    where a grid is any piecewise-constant density."""
    if bins.shape[-1] == 1:
        zero = jnp.zeros((), y.dtype)
        return Figure(zero, zero)
    d = bins.shape[-1]
    values = jnp.reshape(y, (-1, math.prod(y.shape[2:])))
    scale = jnp.max(jnp.abs(values))
    values = values / jnp.where(scale > 0, scale, 1)  # (squares may overflow float32)
    square = jnp.sum(values**2, axis=1)
    tiny = jnp.finfo(square.dtype).tiny
    least = jnp.min(jnp.where(square > 0, square, jnp.inf))
    z = 0.5 * jnp.log(jnp.maximum(jnp.where(square > 0, square, least), tiny))
    # Each point's bin on each axis as a slot of all axes' bins, `(n, d)` in `[0, d * bins)`:
    # bins' sums are one scatter, densities at the points one gather. (Products with a
    # one-hot `(n, d, bins)` array cost more: inside a larger program it was materialised.)
    slots = jnp.reshape(bins, (-1, d)).astype(jnp.int32) + OUTLOOK_BINS * jnp.arange(d)
    split = y.shape[0] // 2 * y.shape[1]
    halves = (slice(0, split), slice(split, None))
    mean_square = jnp.maximum(jnp.sum(jnp.mean(values, axis=0) ** 2), tiny)
    # Each coarser bin's sums, held by every one of the finest bins it covers.
    pooling = np.stack([np.kron(np.eye(count), np.ones((OUTLOOK_BINS // count,) * 2))
                        for count in (2, 4, 8, 16) if count <= OUTLOOK_BINS])

    def log_densities(fit):
        """`(configurations, d, OUTLOOK_BINS)` log densities fitted on the points `fit`."""
        parts = jnp.stack([z[fit], square[fit], jnp.ones_like(z[fit])], axis=-1)  # (n, k)
        on_axes = jnp.broadcast_to(parts[:, None], slots[fit].shape + parts.shape[-1:])
        sums = jax.ops.segment_sum(jnp.reshape(on_axes, (-1, parts.shape[-1])),
                                   jnp.reshape(slots[fit], (-1,)), d * OUTLOOK_BINS)
        sums = jnp.reshape(sums.T, (-1, d, OUTLOOK_BINS))
        pooled = jnp.einsum("kdb,cbe->ckde", sums, jnp.asarray(pooling, z.dtype))
        seen = pooled[:, 2] > 0
        mean_z, mean_square_bin = (pooled[:, k] / jnp.maximum(pooled[:, 2], 1) for k in (0, 1))
        log_q = jnp.stack([mean_z, 0.5 * jnp.log(jnp.maximum(mean_square_bin, tiny))], axis=1)
        seen = seen[:, None]
        # An empty bin gets the axis' mean; every bin at least OUTLOOK_FLOOR of it.
        filled = jnp.sum(jnp.where(seen, log_q, 0), axis=-1, keepdims=True) / jnp.maximum(
            jnp.sum(seen, axis=-1, keepdims=True), 1)
        log_q = jnp.where(seen, log_q, filled)
        log_q = log_q - jnp.max(log_q, axis=-1, keepdims=True)
        log_q = log_q - jnp.log(jnp.mean(jnp.exp(log_q), axis=-1, keepdims=True))
        log_q = jnp.maximum(log_q, math.log(OUTLOOK_FLOOR))
        return jnp.reshape(log_q, (-1, d, OUTLOOK_BINS))

    def read(fit, on):
        """Each configuration's mean of $|f|^2/q$ on the points `on`, and its variance."""
        log_q = jnp.reshape(log_densities(fit), (-1, d * OUTLOOK_BINS))
        at = jnp.sum(log_q[:, slots[on]], axis=-1)  # log q at the points, `(c, n)`
        # (f = 0 adds 0 even where 1/q overflows, never NaN.)
        w = jnp.where(square[on] > 0, square[on] * jnp.exp(-at), 0)
        return jnp.mean(w, axis=1), jnp.var(w, axis=1) / w.shape[1]

    (a, var_a), (b, var_b) = read(*halves), read(*halves[::-1])
    second, second_var = (a + b) / 2, (var_a + var_b) / 4
    outlook = jnp.maximum(second / mean_square - 1, 0)
    # (The standard deviation of log(outlook), by the delta method: that of `second`, relative
    # to the outlook; unbounded for a density that fits f exactly.)
    log_sd = jnp.sqrt(second_var) / jnp.maximum(outlook * mean_square, tiny)
    best = jnp.argmin(outlook)
    seen = jnp.sum(jnp.mean(values, axis=0) ** 2) > 0
    return Figure(jnp.where(seen, outlook[best], jnp.inf), log_sd[best])
