r"""Whether an error bar can be believed: effective sample size, the Pareto tail, rounding floors.

A Monte Carlo mean averages values $c_i = f(x_i)/p(x_i)$ (for multiple
importance sampling, each technique's weighted values scaled by $N/n_k$; for
stratified rules the values themselves, not the allocation's weights, whose
spread says nothing about a tail). Its error bar is only honest when no few of
the $c_i$ dominate. Three statistics of the $c_i$ say so,
and all of them merge exactly over blocks, devices and rounds (`Tail`):

- the **effective sample size** $\mathrm{ESS} = (\sum_i |c_i|)^2 / \sum_i c_i^2$:
  $N$ when all contribute equally, about 1 when one dominates;
- the number of **non-zero** contributions (a density that missed a peak sees
  only zeros, and reports a tiny or zero variance);
- the **Pareto shape** $\hat k$ of the upper tail of $|c_i|$: a generalised
  Pareto distribution fitted to the exceedances of the $M$ largest values over
  the next one, by the profile-posterior method of Zhang and Stephens (2009)
  with the weakly informative prior of Pareto-smoothed importance sampling
  (Vehtari, Simpson, Gelman, Yao and Gabry, 2024), $M = \min(128,\,
  \lfloor\min(N/5,\, 3\sqrt N)\rfloor)$. The variance of $c$ is finite only for
  $k < 1/2$; for $\hat k > 0.7$ the sample variance cannot be trusted at any
  practical $N$.

Besides the statistics, floating point bounds what a mean can claim: a
reported standard error is never below `rounding_floor(dtype)` times the mean
of $|c_i|$ (a few ulps of the integrand's evaluation and of the summation).
"""

from __future__ import annotations

import warnings
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


__all__ = [
    "TAIL",
    "MIN_ESS",
    "MIN_NONZERO",
    "MAX_PARETO_K",
    "MIN_Q",
    "CONSERVATIVE_RATIO",
    "Tail",
    "ReliabilityWarning",
    "rounding_floor",
    "tail_of",
    "largest",
    "tail_sums",
    "empty_tail",
    "merge_tails",
    "gather_tails",
    "stderr_floor",
    "floored_variance",
    "bounded_variance",
    "effective_sample_size",
    "pareto_k",
    "unreliable",
    "reliability_reasons",
    "warn_if_unreliable",
]

TAIL = 128  # largest |c_i| kept for the Pareto fit (plus one: the threshold)
MIN_TAIL = 20  # fewer exceedances give a k-hat too noisy to act on (sd ~0.25 at 20)
MIN_ESS = 10  # below: a handful of values carry the mean and its variance
MIN_NONZERO = 10  # below: a peak was hit a few times or not at all
MAX_PARETO_K = 0.7  # above: the variance estimate cannot be trusted...
HEAVY_TAIL_ESS_SHARE = 0.1  # ...when the tail carries the mean (ess below this share of n)
MIN_Q = 1e-3  # below: adaptive rounds disagree beyond their error bars
# Relative rounding error allowed for the arithmetic behind a mean: a few ulps for the
# integrand's own evaluation (its float32 points and library functions) and the summation.
ROUNDING_ULPS = 4


class ReliabilityWarning(UserWarning):
    """An error bar that cannot be trusted: a heavy tail, a missed peak, dropped values,
    adaptive rounds that disagree, an unmet tolerance."""


def rounding_floor(dtype) -> float:
    r"""The smallest relative standard error an estimate in `dtype` can claim: $4\,\varepsilon$.

    $\varepsilon$ is the dtype's machine epsilon (1.2e-7 in float32, 2.2e-16 in
    float64). Below it the statistical error bar would be smaller than the
    rounding error of the arithmetic that produced the mean, so reported
    standard errors are floored at this fraction of the mean absolute
    contribution, and a tolerance `rtol` below it is refused.
    """
    return ROUNDING_ULPS * float(jnp.finfo(dtype).eps)


class Tail(NamedTuple):
    """Mergeable statistics of contributions $c_i$, per component of the value.

    `count` (scalar float) counts the contributions; `abs_sum` $\\sum|c_i|$,
    `sq_sum` $\\sum c_i^2$ and `nonzero` (float) have the value's shape; `top`
    holds the `TAIL + 1` largest $|c_i|$ in decreasing order along its last
    axis (zeros while fewer were seen).
    """

    count: jax.Array
    abs_sum: jax.Array
    sq_sum: jax.Array
    nonzero: jax.Array
    top: jax.Array


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
def tail_of(c: jax.Array, valid: jax.Array | None = None) -> Tail:
    """The `Tail` of contributions `c` `(n, ...)` (rows where `valid`)."""
    c = jnp.asarray(c)
    if valid is not None:
        mask = jnp.reshape(valid, valid.shape + (1,) * (c.ndim - 1))
        c = jnp.where(mask, c, 0)
        count = jnp.sum(valid).astype(c.dtype)
    else:
        count = jnp.asarray(c.shape[0], c.dtype)
    a = jnp.abs(c)
    return jax.lax.optimization_barrier(Tail(
        count=count,
        abs_sum=jnp.sum(a, axis=0),
        sq_sum=jnp.sum(a * a, axis=0),
        nonzero=jnp.sum(a > 0, axis=0).astype(c.dtype),
        top=largest(a, 0),
    ))


@jax.jit
def tail_sums(c: jax.Array) -> Tail:
    """The `Tail` of contributions `c` `(n, ...)` without their largest values (zeros there):
    its sums only, for a loop that needs the largest values of a few rounds alone (their
    search is half the time of a VEGAS+ round of 2048 points on a CPU)."""
    a = jnp.abs(jnp.asarray(c))
    return Tail(
        count=jnp.asarray(a.shape[0], a.dtype),
        abs_sum=jnp.sum(a, axis=0),
        sq_sum=jnp.sum(a * a, axis=0),
        nonzero=jnp.sum(a > 0, axis=0).astype(a.dtype),
        top=jnp.zeros(a.shape[1:] + (TAIL + 1,), a.dtype),
    )


def empty_tail(shape: tuple[int, ...], dtype) -> Tail:
    zero = jnp.zeros(shape, dtype)
    return Tail(jnp.zeros((), dtype), zero, zero, zero, jnp.zeros(shape + (TAIL + 1,), dtype))


@jax.jit
def merge_tails(a: Tail, b: Tail) -> Tail:
    """Exact merge: sums add, and the largest values of the union are kept."""
    return Tail(
        a.count + b.count,
        a.abs_sum + b.abs_sum,
        a.sq_sum + b.sq_sum,
        a.nonzero + b.nonzero,
        largest(jnp.concatenate([a.top, b.top], axis=-1), -1),
    )


def gather_tails(t: Tail, axes: tuple[str, ...]) -> Tail:
    """Merge per-device tails across mesh `axes` with collectives."""
    # Every device's values placed in its own row and summed: a psum, unlike all_gather,
    # gives a value that is the same on every device (as shard_map's scan carry must be).
    devices = jax.lax.axis_size(axes)
    rows = jnp.zeros((devices,) + t.top.shape, t.top.dtype).at[jax.lax.axis_index(axes)].set(t.top)
    rows = jax.lax.psum(rows, axes)
    top = jnp.concatenate([rows[j] for j in range(devices)], axis=-1)
    return Tail(
        jax.lax.psum(t.count, axes),
        jax.lax.psum(t.abs_sum, axes),
        jax.lax.psum(t.sq_sum, axes),
        jax.lax.psum(t.nonzero, axes),
        largest(top, -1),
    )


def stderr_floor(t: Tail) -> jax.Array:
    r"""The smallest standard error contributions `t` can claim:
    $\mathrm{rounding\_floor}\cdot\frac1N\sum|c_i|$ (per component)."""
    return rounding_floor(t.abs_sum.dtype) * t.abs_sum / jnp.maximum(t.count, 1)


@jax.jit
def floored_variance(variance: jax.Array, t: Tail) -> jax.Array:
    r"""`variance` of the mean, at least `stderr_floor(t)` squared."""
    return jnp.maximum(variance, (stderr_floor(t) ** 2).astype(jnp.result_type(variance)))


# Above this tail shape the values follow a power law (an unbounded integrand, or f/p with a
# singular ratio): variance estimators from few replicas or pairs are skewed and too small.
STRUCTURED_MAX_PARETO_K = 0.2
# ...called on this many exceedances at least (n >= 456): on fewer, k-hat's noise (sd about
# (1 + k)/sqrt(M)) carries bounded tails (k < 0) past 0.2, swapping in a far wider bound.
STRUCTURED_MIN_TAIL = 64
# A bound this many times the structured variance is flagged: an upper bound, not a stderr.
CONSERVATIVE_RATIO = 4.0


@jax.jit
def power_law_tail(t: Tail) -> jax.Array:
    """Whether the contributions have a power-law tail ($\\hat k$ > `STRUCTURED_MAX_PARETO_K`
    on at least `STRUCTURED_MIN_TAIL` exceedances): an unbounded integrand, where structured
    (replica, stratum) spreads understate the error."""
    return (pareto_k(t) > STRUCTURED_MAX_PARETO_K) & (tail_size(t.count) >= STRUCTURED_MIN_TAIL)


@jax.jit
def bounded_variance(variance: jax.Array, mean: jax.Array, t: Tail) -> tuple[jax.Array, jax.Array]:
    r"""A structured variance estimate (replicas of a net, pairs in strata, antithetic
    pairs), made safe for power-law tails; returns `(variance, conservative)`.

    Randomised QMC's variance comes from the $R - 1$ degrees of freedom of its
    replicas, a stratified one from pairs within each stratum. For an unbounded
    integrand ($\hat k > 0.2$, e.g. $x^{-1/3}$ or $x^{-1/2}$) the few values
    that carry the singularity make these estimates skewed and too small. There the i.i.d.
    variance of all contributions, $(\overline{c^2} - \bar c^2)/N$, is reported
    when larger: proportional stratification never has a larger variance, and a
    scrambled $(0, m, s)$-net at most a constant times it (Owen 1997), so it
    bounds the error honestly (conservatively). `conservative` says the bound is
    at least `CONSERVATIVE_RATIO` times the structured estimate: the error bar is
    then an upper bound, usually far above the actual error, and `unreliable` says so.
    """
    count = jnp.maximum(t.count, 1)
    iid = jnp.maximum(t.sq_sum / count - mean**2, 0.0) / count
    heavy = power_law_tail(t)
    conservative = heavy & (iid > CONSERVATIVE_RATIO * variance)
    return jnp.where(heavy, jnp.maximum(variance, iid), variance), conservative


@jax.jit
def effective_sample_size(t: Tail) -> jax.Array:
    r"""$(\sum|c_i|)^2 / \sum c_i^2$ (0 when every contribution is zero)."""
    return jnp.where(t.sq_sum > 0, t.abs_sum**2 / jnp.where(t.sq_sum > 0, t.sq_sum, 1), 0.0)


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
    m_tail = tail_size(count)
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


def variance_out_of_range(est: Any) -> jax.Array:
    r"""Whether `est`'s variance left its dtype's range, per component: infinite with a finite
    mean, or below the smallest normal number (0, or subnormal) with a non-zero one.

    A variance is a square: a standard error above about $10^{19}$ or below $10^{-19}$ in
    float32 ($10^{154}$, $10^{-154}$ in float64) cannot be held, and squares of values
    $f/p$ beyond those bounds over- or underflow on the way to it. A variance of 0 then
    claims an exact mean, which no estimate can (its rounding floor, `rounding_floor` times
    the mean, underflowed as well); an infinite one says nothing."""
    # (Below the smallest normal number a variance is subnormal, with a few bits, or flushed
    # to 0, as the CPU may and GPUs do.)
    tiny = jnp.finfo(jnp.result_type(est.variance, float)).tiny
    return (~jnp.isfinite(est.variance) & jnp.isfinite(est.mean)) | (
        (est.variance < tiny) & (est.mean != 0)
    )


def unreliable(est: Any) -> jax.Array:
    """Whether the diagnostics say `est`'s error bar cannot be trusted (a bool scalar).

    True when any component has a tiny effective sample size (< 10, or < n/4 for
    tiny n), fewer than 10 non-zero contributions (or fewer than n), a Pareto
    $\\hat k$ above 0.7 with an effective sample size below n/10, dropped non-finite values,
    a variance outside its dtype's range (`variance_out_of_range`), a structured variance
    replaced by a much larger i.i.d. bound (`bounded_variance`); for combined rounds a $q$
    below 1e-3; for a tolerance run `converged` False; for an `Expectation` an unreliable
    evidence `norm`.
    Jittable and vmappable (map it over a batch of estimates).
    """
    return jnp.any(jnp.stack([jnp.any(flag) for flag in _flags(est).values()]))


def _flags(est: Any) -> dict[str, jax.Array]:
    # A handful of samples is not a failure when it is all there is: the thresholds
    # shrink with `n` (all n non-zero, or an ess of n/4, is never flagged).
    n = jnp.asarray(est.n).astype(jnp.result_type(float))
    flags = {
        "non-finite integrand values were dropped": est.n_nonfinite > 0,
        f"fewer than {MIN_NONZERO} samples were non-zero (a missed or barely hit peak?)": (
            (est.n_nonzero >= 0) & (est.n_nonzero < jnp.minimum(MIN_NONZERO, n))
        ),
        f"the effective sample size is below {MIN_ESS} (a few samples carry the mean)": (
            est.ess < jnp.minimum(MIN_ESS, n / 4)
        ),
        f"the Pareto tail shape k-hat exceeds {MAX_PARETO_K} (rare large values carry the mean: "
        "a narrow peak sampled too sparsely, or an infinite variance)": (
            (est.pareto_k > MAX_PARETO_K) & (est.ess < HEAVY_TAIL_ESS_SHARE * n)
        ),
        "the variance is outside its dtype's range (infinite, or 0 for a non-zero mean: a "
        "standard error this large or small, or the squares of such values, over- or "
        "underflow); rescale f towards 1, or enable float64 "
        "(jax.config.update('jax_enable_x64', True))": variance_out_of_range(est),
    }
    if hasattr(est, "conservative"):  # an Estimate (any duck-typed result without it: no flag)
        flags[
            "the values have a power-law tail, where the spread of replicas or strata "
            "underestimates the error, and the i.i.d. bound reported instead is over "
            f"{CONSERVATIVE_RATIO:g}x that spread: an upper bound, likely far above the actual "
            "error"
        ] = est.conservative
    if hasattr(est, "q"):
        flags[f"the combined rounds disagree (q < {MIN_Q:g})"] = est.q < MIN_Q
    if getattr(est, "converged", None) is not None:
        flags["the tolerance was not met, or its error bar is not to be trusted"] = (
            ~jnp.asarray(est.converged))
    norm = getattr(est, "norm", None)  # an `Expectation`'s evidence: a ratio's denominator
    if norm is not None:
        flags["the evidence `norm` is unreliable (`reliability_reasons(est.norm)` says why; `log_norm` holds it where it under- or overflows)"] = (
            jnp.any(jnp.stack([jnp.any(flag) for flag in _flags(norm).values()])))
    return flags


def trusted(est: Any) -> jax.Array:
    """`~unreliable(est)`, in one compiled program when run eagerly."""
    return ~jnp.any(_any_flags(est)[1])


def reliability_reasons(est: Any) -> list[str]:
    """The reasons `unreliable(est)` is true, in words (needs concrete values)."""
    reasons, flags = _any_flags(est)
    return [reason for reason, flag in zip(reasons, np.asarray(flags)) if flag]


@eqx.filter_jit
def _any_flags(est: Any) -> tuple[tuple[str, ...], jax.Array]:
    # One compiled program: run eagerly, the flags' dozen small operations each compiled
    # on a first call (~0.3 s); one array, read at once.
    flags = _flags(est)
    return tuple(flags), jnp.stack([jnp.any(flag) for flag in flags.values()])


def warn_if_unreliable(est: Any, where: str, stacklevel: int = 3) -> None:
    """Warn `ReliabilityWarning` with the reasons, outside `jit` (under `jit`: nothing;
    the same facts are on the result)."""
    if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(est)):
        return
    reasons = reliability_reasons(est)
    if reasons:
        warnings.warn(
            f"{where}: the error bar may not be trustworthy: " + "; ".join(reasons) + ".",
            ReliabilityWarning,
            stacklevel=stacklevel,
        )
