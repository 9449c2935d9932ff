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
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._tail import (
    TAIL,
    Tail,
    empty_tail,
    gather_tails,
    largest,
    merge_tails,
    pareto_k,
    pareto_k_on,
    pareto_k_sd,
    tail_of,
    tail_size,
    tail_sums,
)


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
    "pareto_k_sd",
    "tail_size",
    "unreliable",
    "reliability_reasons",
    "warn_if_unreliable",
]

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


def stderr_floor(t: Tail) -> jax.Array:
    r"""The smallest standard error contributions `t` can claim:
    $\mathrm{rounding\_floor}\cdot\frac1N\sum|c_i|$ (per component)."""
    return rounding_floor(t.abs_sum.dtype) * t.abs_sum / jnp.maximum(t.count, 1)


@jax.jit
def floored_variance(variance: jax.Array, t: Tail) -> jax.Array:
    r"""`variance` of the mean, at least `stderr_floor(t)` squared."""
    return jnp.maximum(variance, (stderr_floor(t) ** 2).astype(jnp.result_type(variance)))


# Above this tail shape the values' fourth moment is infinite (it is finite for k < 1/4): a
# spread's own variance is then unbounded, and variance estimators from few replicas or
# pairs are skewed and usually too small (an unbounded integrand, or f/p with a singular
# ratio).
STRUCTURED_MAX_PARETO_K = 0.25
# ...called on this many exceedances at least (n >= 456): on fewer, k-hat's noise (sd about
# (1 + k)/sqrt(M)) carries bounded tails (k < 0) past it, swapping in a far wider bound.
STRUCTURED_MIN_TAIL = 64
# A bound this many times the structured variance is flagged: an upper bound, not a stderr.
CONSERVATIVE_RATIO = 4.0


# A top quarter whose shape reads this many standard deviations lighter than the whole
# tail's is a bounded tail, not a power law (a one-sided test: a power law's top quarter
# reads that much lighter by noise about once in a thousand tails).
THRESHOLD_STABILITY_SIGMAS = 3.0


@jax.jit
def power_law_tail(t: Tail) -> jax.Array:
    """Whether the contributions have a power-law tail: an unbounded integrand, where
    structured (replica, stratum) spreads understate the error.

    Called where $\\hat k$ > `STRUCTURED_MAX_PARETO_K` on at least `STRUCTURED_MIN_TAIL`
    exceedances, unless the largest quarter of them reads bounded. A power law is the same
    at every threshold (the generalised Pareto family is closed under raising it: the
    exceedances over a higher threshold have the same $k$), while values with a finite
    maximum, f/q through a density that tames a peak among them, bend towards it: at
    moderate thresholds a bounded but skewed tail (a product of bounded ratios, near
    log-normal, or a few points in the corner of a box where f/q is largest) reads like a
    power law, and only its top shows the bound. So the top quarter's own $\\hat k_{M/4}$
    is compared with the whole tail's $\\hat k_M$; the tail is bounded when
    $\\hat k_{M/4} < 0$, or when $\\hat k_M - \\hat k_{M/4}$ exceeds
    `THRESHOLD_STABILITY_SIGMAS` times its standard deviation under a power law,
    $\\sqrt{\\sigma^2_{M/4} - \\sigma^2_M}$ (nested estimates: the larger sample's
    variance is the shared part), with $\\sigma_m$ that of a shape fitted to $m$ exceedances
    (`pareto_k_sd`).

    Where the contributions are $f/q$ for a density bounded below, $q \\ge q_0 > 0$ (a
    grid's), $f/q \\le f/q_0$: the tail of $f/q$ has the same index as that of $f$'s own
    values, and is bounded where $f$ is. The values of $f/q$ often are not clean: at
    moderate sizes a grid that tames a peak leaves a long bounded tail, $f/q$ rising towards
    the inner edges of its outer bins, that reads as a power law at every threshold the
    sample reaches. $f$'s own largest values (`Tail.f_top`) show the bound there: a peak's
    cluster below its maximum ($\\hat k < 0$), and a singularity's keep the power law. So
    the call also needs $f$'s tail not light, $\\hat k_f > 0$ (a generalised Pareto tail with
    $k \\le 0$ has every moment); a tail of index $1/4$ reads $\\hat k_f \\le 0$ by noise
    with probability about $\\Phi(-2.5)$ on 128 exceedances. Where no $f$ was given,
    `f_top` is `top` and this adds nothing."""
    size = tail_size(t.count)
    quarter = jnp.floor(size / 4)
    k = pareto_k(t)
    top, f_top = jax.lax.optimization_barrier((t.top, t.f_top))
    top_k = pareto_k_on(top, quarter)
    spread = jnp.sqrt(jnp.maximum(
        pareto_k_sd(k, quarter) ** 2 - pareto_k_sd(k, size) ** 2, 0.0))
    bends = (top_k < 0) | (k - top_k > THRESHOLD_STABILITY_SIGMAS * spread)
    f_light = pareto_k_on(f_top, size) <= 0
    return (k > STRUCTURED_MAX_PARETO_K) & (size >= STRUCTURED_MIN_TAIL) & ~bends & ~f_light


@jax.jit
def bounded_variance(variance: jax.Array, mean: jax.Array, t: Tail) -> tuple[jax.Array, jax.Array]:
    r"""A structured variance estimate (replicas of a net, pairs in strata, antithetic
    pairs), made safe for power-law tails; returns `(variance, conservative)`.

    Randomised QMC's variance comes from the $R - 1$ degrees of freedom of its
    replicas, a stratified one from pairs within each stratum. For an unbounded
    integrand ($\hat k > 1/4$, e.g. $x^{-1/3}$ or $x^{-1/2}$) the few values
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
    $\\hat k$ above 0.7 with an effective sample size below n/10, dropped non-finite
    values (not those `integrate(..., nonfinite="drop")` drops on request), a variance
    outside its dtype's range (`variance_out_of_range`), a structured variance
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
        # (`integrate(..., nonfinite="drop")` drops them on request: not news.)
        "non-finite integrand values were seen (counted in `n_nonfinite`)": (
            (est.n_nonfinite > 0) & (getattr(est, "nonfinite", "raise") != "drop")),
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
    beyond = getattr(est, "tail_beyond_map", None)  # `integrate` with infinite limits
    if beyond is not None:
        flags["the integrand decays so slowly along an infinite axis that the share of the "
              "integral beyond the reach of the map of its infinite limits (never sampled) "
              "exceeds the error bar: the estimate falls short; enable float64 or transform "
              "the tail"] = jnp.asarray(beyond)
    if hasattr(est, "q"):
        flags[f"the combined rounds disagree (q < {MIN_Q:g})"] = est.q < MIN_Q
    if getattr(est, "converged", None) is not None:
        flags["the tolerance was not met, or its error bar is not to be trusted"] = (
            ~jnp.asarray(est.converged))
    norm = getattr(est, "norm", None)  # an `Expectation`'s evidence: a ratio's denominator
    if norm is not None:
        # (An evidence whose error bar is a conservative bound leaves the ratio's own alone.)
        norm_flags = _flags(eqx.tree_at(lambda e: e.conservative, norm,
                                        jnp.zeros_like(norm.conservative)))
        flags["the evidence `norm` is unreliable (`reliability_reasons(est.norm)` says why; `log_norm` holds it where it under- or overflows)"] = (
            jnp.any(jnp.stack([jnp.any(flag) for flag in norm_flags.values()])))
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
