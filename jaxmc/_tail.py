r"""The tail of a sample of contributions: mergeable statistics and its Pareto shape.

A Monte Carlo mean averages contributions $c_i = f(x_i)/p(x_i)$; whether its
error bar can be believed depends on how their largest values behave. `Tail`
holds what that needs and merges exactly over blocks, devices and rounds: the
count, $\sum|c_i|$, $\sum c_i^2$, the non-zero count and the `TAIL + 1` largest
$|c_i|$ (and $|f(x_i)|$ where a grid's density divides $f$). `pareto_k` fits a
generalised Pareto distribution to the exceedances of the largest of them over the
next one (Zhang and Stephens, 2009, with the prior of Pareto-smoothed importance
sampling: Vehtari, Simpson, Gelman, Yao and Gabry, 2024). `jaxmc._diagnostics` reads them.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np


TAIL = 128  # largest |c_i| kept for the Pareto fit (plus one: the threshold)
MIN_TAIL = 20  # fewer exceedances give a k-hat too noisy to act on (sd ~0.25 at 20)


class Tail(NamedTuple):
    """Mergeable statistics of contributions $c_i$, per component of the value.

    `count` (scalar float) counts the contributions; `abs_sum` $\\sum|c_i|$,
    `sq_sum` $\\sum c_i^2$ and `nonzero` (float) have the value's shape; `top`
    holds the `TAIL + 1` largest $|c_i|$ in decreasing order along its last
    axis (zeros while fewer were seen); `f_top` the same of the integrand's own values
    $|f(x_i)|$ where $c_i = f(x_i)/q(x_i)$ for a density $q$ bounded below (a grid's), and
    `top` again where the caller gives no $f$ (a uniform density, where $c \\propto f$).
    """

    count: jax.Array
    abs_sum: jax.Array
    sq_sum: jax.Array
    nonzero: jax.Array
    top: jax.Array
    f_top: jax.Array


# Groups of this many entries in which `largest` looks for the largest ones first.
_GROUP = 16


def largest(a: jax.Array, axis: int) -> jax.Array:
    r"""The `TAIL + 1` largest entries of `a >= 0` along `axis`, moved last, decreasing (zero padded).

    Where there are many entries (a stream's block of $2^{14}$), the search
    narrows first to the `TAIL + 1` groups of `_GROUP` consecutive entries
    with the largest maxima: they hold the largest entries, since each of those
    maxima is at least the `(TAIL + 1)`-th largest entry. Selecting among the
    group maxima and then among the $16 \cdot 129$ entries of the chosen groups
    costs about half a selection among all $2^{14}$ in float64.

    Wider than float32, the entries are ranked by $\log(a/\max a)$ in float32 and
    the chosen ones gathered at full precision and sorted: XLA's CPU `top_k` is
    a partial selection in float32 but a full sort in float64. The logarithm keeps
    the whole float64 range apart; two entries can swap ranks only when they
    differ by less than about $6\cdot10^{-8}\,|\log(a/\max a)|$ relative, where
    the Pareto fit learns nothing from the difference.
    """
    a = jnp.moveaxis(a, axis, -1)
    keep = TAIL + 1
    short = keep - a.shape[-1]
    if short > 0:
        a = jnp.concatenate([a, jnp.zeros(a.shape[:-1] + (short,), a.dtype)], axis=-1)
    if a.shape[-1] >= 4 * keep * _GROUP:
        spare = -a.shape[-1] % _GROUP  # zeros rank last, as the padding above
        a = jnp.concatenate([a, jnp.zeros(a.shape[:-1] + (spare,), a.dtype)], axis=-1)
        groups = jnp.reshape(a, a.shape[:-1] + (-1, _GROUP))
        chosen = _top_indices(jnp.max(groups, axis=-1), keep)
        a = jnp.reshape(jnp.take_along_axis(groups, chosen[..., None], axis=-2),
                        a.shape[:-1] + (keep * _GROUP,))
    top = jnp.take_along_axis(a, _top_indices(a, keep), axis=-1)
    return -jnp.sort(-top, axis=-1)


def _top_indices(a: jax.Array, k: int) -> jax.Array:
    """Indices of the `k` largest entries of `a >= 0` along the last axis (ranked in float32)."""
    if jnp.finfo(a.dtype).bits <= 32:
        return jax.lax.top_k(a, k)[1]
    scale = jnp.max(a, axis=-1, keepdims=True)
    ranks = jnp.log(a / jnp.where(scale > 0, scale, 1)).astype(jnp.float32)
    return jax.lax.top_k(ranks, k)[1]


@jax.jit
def tail_of(c: jax.Array, valid: jax.Array | None = None, f: jax.Array | None = None) -> Tail:
    """The `Tail` of contributions `c` `(n, ...)` (rows where `valid`), with `f` `(n, ...)`
    the integrand's values where `c` is $f/q$ for a density $q$ bounded below."""
    c = jnp.asarray(c)
    if valid is not None:
        mask = jnp.reshape(valid, valid.shape + (1,) * (c.ndim - 1))
        c = jnp.where(mask, c, 0)
        f = None if f is None else jnp.where(mask, jnp.asarray(f), 0)
        count = jnp.sum(valid).astype(c.dtype)
    else:
        count = jnp.asarray(c.shape[0], c.dtype)
    a = jnp.abs(c)
    top = largest(a, 0)
    if f is None:
        f_top = top
    else:
        f_top = largest(jnp.abs(jnp.where(jnp.isfinite(f), f, 0)).astype(c.dtype), 0)
    return jax.lax.optimization_barrier(Tail(
        count=count,
        abs_sum=jnp.sum(a, axis=0),
        sq_sum=jnp.sum(a * a, axis=0),
        nonzero=jnp.sum(a > 0, axis=0).astype(c.dtype),
        top=top,
        f_top=f_top,
    ))


@jax.jit
def tail_sums(c: jax.Array) -> Tail:
    """The `Tail` of contributions `c` `(n, ...)` without their largest values (zeros there):
    its sums only, for a loop that needs the largest values of a few rounds alone (their
    search is half the time of a VEGAS+ round of 2048 points on a CPU)."""
    a = jnp.abs(jnp.asarray(c))
    top = jnp.zeros(a.shape[1:] + (TAIL + 1,), a.dtype)
    return Tail(
        count=jnp.asarray(a.shape[0], a.dtype),
        abs_sum=jnp.sum(a, axis=0),
        sq_sum=jnp.sum(a * a, axis=0),
        nonzero=jnp.sum(a > 0, axis=0).astype(a.dtype),
        top=top,
        f_top=top,
    )


def empty_tail(shape: tuple[int, ...], dtype) -> Tail:
    zero = jnp.zeros(shape, dtype)
    top = jnp.zeros(shape + (TAIL + 1,), dtype)
    return Tail(jnp.zeros((), dtype), zero, zero, zero, top, top)


@jax.jit
def merge_tails(a: Tail, b: Tail) -> Tail:
    """Exact merge: sums add, and the largest values of the union are kept."""
    return Tail(
        a.count + b.count,
        a.abs_sum + b.abs_sum,
        a.sq_sum + b.sq_sum,
        a.nonzero + b.nonzero,
        largest(jnp.concatenate([a.top, b.top], axis=-1), -1),
        largest(jnp.concatenate([a.f_top, b.f_top], axis=-1), -1),
    )


def gather_tails(t: Tail, axes: tuple[str, ...]) -> Tail:
    """Merge per-device tails across mesh `axes` with collectives."""
    # Every device's values placed in its own row and summed: a psum, unlike all_gather,
    # gives a value that is the same on every device (as shard_map's scan carry must be).
    devices = jax.lax.axis_size(axes)

    def gathered(top):
        rows = jnp.zeros((devices,) + top.shape, top.dtype).at[jax.lax.axis_index(axes)].set(top)
        rows = jax.lax.psum(rows, axes)
        return largest(jnp.concatenate([rows[j] for j in range(devices)], axis=-1), -1)

    return Tail(
        jax.lax.psum(t.count, axes),
        jax.lax.psum(t.abs_sum, axes),
        jax.lax.psum(t.sq_sum, axes),
        jax.lax.psum(t.nonzero, axes),
        gathered(t.top),
        gathered(t.f_top),
    )


# Zhang and Stephens's profile grid and prior, as in PSIS.
_PRIOR_BS = 3.0
_PRIOR_K = 10.0
_GRID = 30 + int(np.sqrt(TAIL))


def tail_size(count: jax.Array) -> jax.Array:
    """The exceedances $M$ the Pareto fit uses among `count` contributions (as PSIS)."""
    return jnp.floor(jnp.minimum(jnp.minimum(count / 5, 3 * jnp.sqrt(count)), TAIL))


@jax.jit
def pareto_k(t: Tail) -> jax.Array:
    r"""Generalised Pareto shape $\hat k$ of the upper tail of $|c_i|$ (per component).

    With $M$ exceedances $x_{(1)} \le \dots \le x_{(M)}$ of the largest values
    over the $(M+1)$-th, Zhang and Stephens's estimate is a posterior mean over
    a grid of $\theta_j = 1/x_{(M)} + (1 - \sqrt{m/(j - 1/2)})/(3 x_{(q)})$,
    $q = \lfloor M/4 + 1/2\rfloor$, $j = 1..m$, $m = 30 + \lfloor\sqrt M\rfloor$,
    each weighted by its profile likelihood $M(\log(-\theta_j/k_j) - k_j - 1)$
    with $k_j = \frac1M \sum_i \log(1 - \theta_j x_{(i)})$; then $\hat k =
    \frac1M\sum_i\log(1 - \bar\theta x_{(i)})$ at the posterior mean
    $\bar\theta$, shrunk towards 1/2 by a prior worth 10 observations.
    NaN with fewer than 100 contributions (too short a tail), $-\infty$ when the
    largest values are all equal (a bounded integrand's flat top).
    """
    # The barrier keeps XLA from fusing the tail's `top_k` into the gathers below, which
    # on the CPU turned an O(n) pass into a full sort (1.5 s instead of 10 ms at n = 2^22).
    count, top = jax.lax.optimization_barrier((t.count, t.top))
    return pareto_k_on(top, tail_size(count))


def pareto_k_sd(k: jax.Array, m_tail: jax.Array, *, prior: bool = True) -> jax.Array:
    r"""The standard deviation of a generalised Pareto shape $k$ estimated on `m_tail`
    exceedances: the maximum-likelihood estimate's $(1 + k)/\sqrt M$ (Smith, 1987, for
    $k > -1/2$), with `prior` scaled by `pareto_k`'s shrinkage $M/(M + 10)$."""
    m = jnp.maximum(m_tail, 1)
    sd = (1 + jnp.maximum(k, -0.5)) / jnp.sqrt(m)
    return sd * m / (m + _PRIOR_K) if prior else sd


def pareto_k_on(top: jax.Array, m_tail: jax.Array) -> jax.Array:
    """`pareto_k`'s estimate on the `m_tail` exceedances over `top[m_tail]`."""
    m_int = m_tail.astype(jnp.int32)
    idx = jnp.arange(TAIL + 1)
    threshold = jnp.take_along_axis(
        top, jnp.broadcast_to(m_int, top.shape[:-1] + (1,)), axis=-1
    )
    in_tail = idx[:-1] < m_int
    x = jnp.where(in_tail, top[..., :-1] - threshold, 0.0)  # decreasing; x[0] the largest
    x_max = x[..., :1]
    # The quartile x_(ceil(M/4)) in increasing order is at decreasing index M - ceil(M/4 + 1/2) + 1.
    quart_at = m_int - jnp.floor(m_tail / 4 + 0.5).astype(jnp.int32)
    x_quart = jnp.take_along_axis(x, jnp.broadcast_to(quart_at, x.shape[:-1] + (1,)), axis=-1)
    safe_max = jnp.where(x_max > 0, x_max, 1.0)
    safe_quart = jnp.where(x_quart > 0, x_quart, safe_max)
    grid_size = 30 + jnp.floor(jnp.sqrt(m_tail))
    j = jnp.arange(1, _GRID + 1, dtype=top.dtype)
    on_grid = j <= grid_size
    theta = 1 / safe_max + (1 - jnp.sqrt(grid_size / jnp.where(on_grid, j - 0.5, 1.0))) / (
        _PRIOR_BS * safe_quart
    )  # (..., grid)
    terms = jnp.log1p(-theta[..., :, None] * x[..., None, :])
    mean_log = jnp.sum(jnp.where(in_tail, terms, 0.0), axis=-1) / jnp.maximum(m_tail, 1)
    k_grid = mean_log
    log_like = m_tail * (jnp.log(-theta / jnp.where(k_grid != 0, k_grid, 1.0)) - k_grid - 1)
    log_like = jnp.where(on_grid & (k_grid != 0) & jnp.isfinite(log_like), log_like, -jnp.inf)
    weights = jax.nn.softmax(log_like, axis=-1)
    theta_post = jnp.sum(weights * theta, axis=-1, keepdims=True)
    k_post = jnp.sum(
        jnp.where(in_tail, jnp.log1p(-theta_post * x), 0.0), axis=-1
    ) / jnp.maximum(m_tail, 1)
    k = (m_tail * k_post + _PRIOR_K * 0.5) / (m_tail + _PRIOR_K)
    k = jnp.where(x_max[..., 0] > 0, k, -jnp.inf)
    return jnp.where(m_tail >= MIN_TAIL, k, jnp.nan)
