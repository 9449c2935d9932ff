r"""Estimates with error bars, their combination, and mergeable running moments.

An `Estimate` is what every estimator returns: the integral estimate, the
estimated variance *of that estimate* (for $n$ i.i.d. samples $\sigma^2/n$;
Owen, *Monte Carlo theory, methods and examples*, ch. 2), the number of integrand
evaluations and the number of them whose value was not finite.

`Moments` are the sufficient statistics `(count, mean, m2)` of a stream of
values, where `m2` is the sum of squared deviations from the mean. Two sets
merge exactly with the parallel update of Chan, Golub and LeVeque (1979):

$$\delta = \bar x_b - \bar x_a,\quad n = n_a + n_b,\quad
\bar x = \bar x_a + \delta\, n_b/n,\quad M_2 = M_{2,a} + M_{2,b} + \delta^2 n_a n_b/n.$$

Merging per-block moments instead of keeping one running sum keeps float32
accurate over $10^9$ samples: each block's mean is a short sum, and the merge
never adds a small number to a huge one.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.scipy.special import betainc, ndtri, polygamma

from ._diagnostics import (
    ReliabilityWarning as ReliabilityWarning,
    Tail,
    bounded_variance,
    effective_sample_size,
    empty_tail,
    floored_variance,
    gather_tails,
    largest,
    merge_tails,
    pareto_k,
    reliability_reasons as reliability_reasons,
    rounding_floor as rounding_floor,
    tail_of,
    tail_sums,
    unreliable as unreliable,
)
from ._format import estimate_repr, estimate_str


class Estimate(eqx.Module):
    r"""A Monte Carlo estimate and its error.

    **Fields:**

    - `mean`: the integral estimate, with the shape of the integrand's output.
    - `variance`: estimated variance of `mean` (for i.i.d. samples $s^2/n$, eq. 13).
    - `n`: number of integrand evaluations.
    - `n_nonfinite`: evaluations whose weighted value $f/p$ was not finite; they
      contributed zero to `mean`.

    Diagnostics (see `unreliable`), per component of the value; an `Estimate`
    built by hand without them has NaN (and `n_nonzero` -1, unknown):

    - `ess`: effective sample size $(\sum_i|c_i|)^2/\sum_i c_i^2$ of the
      contributions $c_i$ (values $f/p$, weighted by stratum where stratified)
      that made the mean: `n` when all contribute equally, about 1 when one
      dominates.
    - `n_nonzero`: contributions that were not zero.
    - `pareto_k`: the generalised Pareto shape $\hat k$ of the upper tail of
      $|c_i|$ (as in Pareto-smoothed importance sampling); the variance is
      finite only for $k < 1/2$, and above 0.7 with `ess` below n/10 (the tail
      carries the mean) the error bar cannot be trusted (`unreliable` flags it;
      with a larger `ess`, as for a singular ratio in a sliver of the box, many
      values share the mean and the error bar holds).
    - `conservative`: the variance is not the estimator's own (the spread of
      replicas, strata or antithetic pairs) but the i.i.d. variance of the
      contributions, over 4 times larger, reported because a power-law tail
      makes the spread unreliable: an upper bound (`bounded_variance`).
    - `dof`: degrees of freedom of `variance`: $R-1$ when it is the spread of $R$
      replicas (randomised QMC), $\infty$ (normal) for sums of many i.i.d. values.
      `interval` uses Student's $t$ with these; $\mathrm{mean} \pm 2\,\mathrm{stderr}$
      covers $P(|t_{R-1}| \le 2)$: 0.82 for 3 replicas, 0.88 for 5, 0.91 for 8.

    `print(est)` shows the compact notation of vegas and gvar, `0.9977(42)` for
    0.99771 ± 0.00423 (element by element for an array); `repr(est)` the numbers.
    """

    mean: jax.Array
    variance: jax.Array
    n: jax.Array
    n_nonfinite: jax.Array
    ess: jax.Array = eqx.field(default=float("nan"), kw_only=True)
    n_nonzero: jax.Array = eqx.field(default=-1, kw_only=True)
    pareto_k: jax.Array = eqx.field(default=float("nan"), kw_only=True)
    conservative: jax.Array = eqx.field(default=False, kw_only=True)
    dof: jax.Array = eqx.field(default=float("inf"), kw_only=True)

    @property
    def stderr(self) -> jax.Array:
        """Standard error $\\sqrt{\\mathrm{variance}}$."""
        return jnp.sqrt(self.variance)

    def interval(self, level: float = 0.95) -> tuple[jax.Array, jax.Array]:
        r"""Confidence interval $\mathrm{mean} \pm t_{(1+\ell)/2,\,\nu}\,\mathrm{stderr}$.

        $t_{p,\nu}$ is Student's $t$ quantile with $\nu$ = `dof` degrees of freedom
        (the spread of $R$ replicas has $R - 1$); for $\nu = \infty$ it is the
        normal (CLT) quantile $z_p$.
        """
        check_level(level)
        p = jnp.asarray(0.5 + level / 2, dtype=jnp.result_type(self.mean))
        half = student_t_quantile(p, self.dof) * self.stderr
        return self.mean - half, self.mean + half

    def chebyshev(self, delta: float) -> jax.Array:
        r"""Half-width $\varepsilon$ with $P(|\mathrm{mean} - I| \ge \varepsilon) \le \delta$.

        Chebyshev's inequality (eq. 14): $\varepsilon = \sqrt{\mathrm{variance}/\delta}$.
        Holds for any distribution with finite variance, so it is wider than
        `interval` but needs no normality.
        """
        if not isinstance(delta, jax.core.Tracer) and not 0 < float(delta) <= 1:
            raise ValueError(f"`delta` must be in (0, 1], got {delta}.")
        return jnp.sqrt(self.variance / delta)

    def __repr__(self) -> str:
        return estimate_repr(self, Estimate)

    def __str__(self) -> str:
        """The mean and its standard error in the compact notation, e.g. `0.9977(42)`."""
        return estimate_str(self)


@jax.jit
def student_t_quantile(p: jax.Array, dof: jax.Array) -> jax.Array:
    r"""The quantile $t_{p,\nu}$ of Student's $t$ with $\nu$ = `dof` degrees of freedom; the
    normal quantile $z_p$ for $\nu = \infty$.

    For $p > 1/2$: $P(T > t) = \frac12 I_{\nu/(\nu+t^2)}(\nu/2, 1/2)$ (the regularised
    incomplete beta function), so $x = \nu/(\nu+t^2)$ solves $I_x(\nu/2, 1/2) = 2(1-p)$;
    found by bisection on $(0, 1]$ (64 halvings, monotone in $x$: to the dtype's
    resolution even for $\nu = 1$, where $t_{0.9995} \approx 637$), then $t =
    \sqrt{\nu(1-x)/x}$; $t_{1-p} = -t_p$. Works under `jit`, no SciPy at run time.
    """
    p = jnp.asarray(p, dtype=jnp.result_type(p, float))
    dof = jnp.asarray(dof, dtype=p.dtype)
    finite = jnp.isfinite(dof) & (dof > 0)
    nu = jnp.where(finite, dof, 1.0)
    upper = jnp.where(p > 0.5, p, 1.0 - p)
    target = 2.0 * (1.0 - upper)

    def halve(_, bounds):
        low, high = bounds
        mid = 0.5 * (low + high)
        below = betainc(nu / 2, jnp.asarray(0.5, p.dtype), mid) < target  # x too small
        return jnp.where(below, mid, low), jnp.where(below, high, mid)

    shape = jnp.broadcast_shapes(p.shape, nu.shape)
    start = (jnp.zeros(shape, p.dtype), jnp.ones(shape, p.dtype))
    low, high = jax.lax.fori_loop(0, 64, halve, start)
    x = jnp.maximum(0.5 * (low + high), jnp.finfo(p.dtype).tiny)
    t = jnp.sqrt(nu * (1.0 - x) / x)
    return jnp.where(finite, jnp.where(p > 0.5, t, -t), ndtri(p))


# The rounds whose means' scatter checks the last round's own variance.
SCATTER_ROUNDS = 5


def scatter_bound(means: jax.Array, round_size: int, z) -> jax.Array:
    r"""A pessimistic bound on the relative variance per evaluation of rounds of `round_size`
    evaluations, from the scatter of their estimates `means` `(rounds, ...)` of one integral.

    The last `SCATTER_ROUNDS` means (or all, if fewer) give the sample variance $s^2$ with $k$
    = their count less one degrees of freedom; $\log s^2$ has standard deviation
    $\sqrt{\psi'(k/2)}$ (the logarithm of a $\chi^2_k$ variable), and the bound is `z` of them
    above: $s^2\,m/\bar\mu^2 \cdot e^{z\sqrt{\psi'(k/2)}}$. Rounds of a grid still adapting
    scatter more than its last: the bound errs high. Summed over an array's components (one
    whose rounds average 0 adds its plain variance); `inf` where it cannot be read (fewer
    than two rounds, values not finite)."""
    recent = means[-SCATTER_ROUNDS:]
    k = recent.shape[0] - 1
    if k < 1:
        return jnp.full((), jnp.inf, means.dtype)
    centre = jnp.mean(recent, axis=0)
    variance = jnp.var(recent, axis=0, ddof=1)
    tiny = jnp.finfo(means.dtype).tiny
    # (A component whose rounds all read 0 adds its variance, 0, not a ratio.)
    relative = jnp.sum(jnp.where(centre != 0, variance / jnp.maximum(centre**2, tiny), variance))
    bound = relative * round_size * jnp.exp(z * jnp.sqrt(polygamma(1, k / 2.0)))
    return jnp.where(jnp.isfinite(bound), bound, jnp.inf)


def check_level(level: float) -> None:
    """A confidence level in (0, 1) (checked when concrete)."""
    if not isinstance(level, jax.core.Tracer) and not 0 < float(level) < 1:
        raise ValueError(f"`level` must be in (0, 1), got {level}.")


def estimate_fields(e: Estimate) -> dict[str, jax.Array]:
    """The `Estimate` fields of `e` (of any subclass), diagnostics included, by name."""
    return {f.name: getattr(e, f.name) for f in dataclasses.fields(Estimate)}


class Moments(NamedTuple):
    """Mergeable sufficient statistics of a stream of values.

    `count` is a float (so weights and huge counts need no integer overflow
    care); `mean` and `m2` have the shape of one value. `tail`, when kept, holds
    the diagnostics of the contributions behind them (`Tail`).
    """

    count: jax.Array
    mean: jax.Array
    m2: jax.Array
    tail: Tail | None = None


def moments(values: jax.Array, mask: jax.Array | None = None) -> Moments:
    """Moments of `values` along axis 0 (two-pass: mean, then centred squares).

    `mask` (shape `(n,)`, bool) selects which rows count.
    """
    values = jnp.asarray(values)
    if mask is None:
        count = jnp.asarray(values.shape[0], dtype=values.dtype)
        mean = jnp.mean(values, axis=0)
        m2 = jnp.sum((values - mean) ** 2, axis=0)
        return Moments(count, mean, m2)
    m = jnp.reshape(mask, mask.shape + (1,) * (values.ndim - 1)).astype(values.dtype)
    count = jnp.sum(mask).astype(values.dtype)
    safe = jnp.maximum(count, 1)
    mean = jnp.sum(values * m, axis=0) / safe
    m2 = jnp.sum(m * (values - mean) ** 2, axis=0)
    return Moments(count, mean, m2)


def merge(a: Moments, b: Moments) -> Moments:
    """Chan et al.'s exact merge of two sets of moments (either may be empty)."""
    count = a.count + b.count
    safe = jnp.where(count > 0, count, 1)
    delta = b.mean - a.mean
    frac_b = _expand(b.count / safe, delta)
    mean = a.mean + delta * frac_b
    m2 = a.m2 + b.m2 + delta**2 * _expand(a.count, delta) * frac_b
    tail = None if a.tail is None else merge_tails(a.tail, b.tail)
    return Moments(count, mean, m2, tail)


def _expand(count: jax.Array, like: jax.Array) -> jax.Array:
    """Append unit axes so per-row counts broadcast against per-row values."""
    return jnp.reshape(count, jnp.shape(count) + (1,) * (jnp.ndim(like) - jnp.ndim(count)))


def merge_all(stacked: Moments) -> Moments:
    r"""Merge moments stacked along axis 0 at once: $N = \sum_i n_i$,
    $\bar x = \sum_i n_i \bar x_i / N$, $M_2 = \sum_i M_{2,i} + \sum_i n_i (\bar x_i - \bar x)^2$
    (Chan, Golub and LeVeque's update for $k$ parts: exact, two passes over the parts)."""
    count = jnp.sum(stacked.count, axis=0)
    weight = _expand(stacked.count / jnp.where(count > 0, count, 1), stacked.mean)
    mean = jnp.sum(weight * stacked.mean, axis=0)
    spread = _expand(stacked.count, stacked.mean) * (stacked.mean - mean) ** 2
    m2 = jnp.sum(stacked.m2, axis=0) + jnp.sum(spread, axis=0)
    tail = None
    if stacked.tail is not None:
        t = stacked.tail

        def pooled(top):
            top = jnp.moveaxis(top, 0, -2)
            return largest(jnp.reshape(top, top.shape[:-2] + (-1,)), -1)

        tail = Tail(jnp.sum(t.count, axis=0), jnp.sum(t.abs_sum, axis=0),
                    jnp.sum(t.sq_sum, axis=0), jnp.sum(t.nonzero, axis=0), pooled(t.top),
                    pooled(t.f_top))
    return Moments(count, mean, m2, tail)


def empty_moments(shape: tuple[int, ...], dtype) -> Moments:
    zero = jnp.zeros(shape, dtype)
    return Moments(jnp.zeros((), dtype), zero, zero, empty_tail(shape, dtype))


def diagnosed(
    mean: jax.Array,
    variance: jax.Array,
    n: jax.Array,
    n_nonfinite: jax.Array,
    tail: Tail,
    conservative: jax.Array | bool = False,
    dof: jax.Array | float = float("inf"),
) -> dict[str, jax.Array]:
    """`Estimate`'s fields from a mean, its variance (with `dof` degrees of freedom) and the
    `Tail` of its contributions: the variance floored at the dtype's rounding error, and the
    diagnostics. A `conservative` variance is the i.i.d. one of all contributions: its
    degrees of freedom are unbounded, whatever `dof` says."""
    conservative = jnp.broadcast_to(jnp.asarray(conservative), jnp.shape(mean))
    return dict(
        conservative=conservative,
        dof=jnp.where(conservative, jnp.inf, jnp.asarray(dof, jnp.result_type(mean))),
        mean=mean,
        variance=floored_variance(variance, tail),
        n=n,
        n_nonfinite=n_nonfinite,
        ess=effective_sample_size(tail),
        n_nonzero=tail.nonzero.astype(jnp.int32),
        pareto_k=pareto_k(tail),
    )


def estimate_from_moments(m: Moments, n: jax.Array, n_nonfinite: jax.Array) -> Estimate:
    """The i.i.d. estimate: mean, and variance of the mean $s^2/n$ with $s^2 = M_2/(n-1)$."""
    count = _expand(m.count, m.m2)
    var = m.m2 / jnp.maximum(count - 1, 1) / jnp.maximum(count, 1)
    var = jnp.where(count > 1, var, jnp.inf)
    if m.tail is None:
        return Estimate(mean=m.mean, variance=var, n=n, n_nonfinite=n_nonfinite)
    return Estimate(**diagnosed(m.mean, var, n, n_nonfinite, m.tail))


def estimate_iid(y: jax.Array, bad: jax.Array) -> Estimate:
    """The basic estimate from per-sample values `y` (shape `(n, ...)`), eq. 12 and 13."""
    n = y.shape[0]
    m = moments(y)._replace(tail=tail_of(y))
    return estimate_from_moments(m, jnp.asarray(n, dtype=jnp.int32), jnp.sum(bad, dtype=jnp.int32))


# Lanes of the two-level reduction inside a block: sums of 128 rows, then a tree.
_LANE = 128


def block_moments(y: jax.Array, valid: jax.Array, with_tail: bool = True) -> Moments:
    """Moments of one block of values `(n, ...)` (rows where `valid`) in two passes, each sum
    over lanes of 128 rows and then across them (float32 stays accurate over a block);
    without their `Tail` unless `with_tail` (a caller that holds many blocks finds their
    largest values at once)."""
    block = y.shape[0]
    lane = min(_LANE, block)
    rows = -(-block // lane)
    if rows * lane != block:  # e.g. a jittered grid of 25^3 points: pad with invalid rows
        pad = rows * lane - block
        y = jnp.concatenate([y, jnp.zeros((pad,) + y.shape[1:], y.dtype)])
        valid = jnp.concatenate([valid, jnp.zeros(pad, bool)])
    mask = jnp.reshape(valid, valid.shape + (1,) * (y.ndim - 1)).astype(y.dtype)

    def total(a):  # sum over rows, lane by lane
        return jnp.sum(jnp.sum(jnp.reshape(a, (rows, lane) + a.shape[1:]), axis=1), axis=0)

    count = jnp.sum(valid).astype(y.dtype)
    mean = total(y * mask) / jnp.maximum(count, 1)
    m = Moments(count, mean, total(mask * (y - mean) ** 2))
    return m._replace(tail=tail_of(y, valid)) if with_tail else m


def merge_across_devices(m: Moments, axes: tuple[str, ...]) -> Moments:
    """Merge per-device moments (scalar counts) across mesh `axes` with collectives.

    The same update as `merge`, written as sums: `psum` of counts, of
    count-weighted means, and of centred second moments about the pooled mean.
    """
    count = jax.lax.psum(m.count, axes)
    safe = _expand(jnp.where(count > 0, count, 1), m.mean)
    weight = _expand(m.count, m.mean)  # per-replica counts against (replicas, ...) values
    mean = jax.lax.psum(weight * m.mean, axes) / safe
    m2 = jax.lax.psum(m.m2 + weight * (m.mean - mean) ** 2, axes)
    tail = None if m.tail is None else gather_tails(m.tail, axes)
    return Moments(count, mean, m2, tail)


def slot_of_sample(counts: jax.Array, n: int) -> jax.Array:
    """The stratum (slot) of each of `n` samples laid out stratum by stratum, `counts` per
    stratum (zeros allowed): `(n,)` non-decreasing indices."""
    starts = jnp.cumsum(counts)[:-1]
    return jnp.cumsum(jnp.zeros((n,), jnp.int32).at[starts].add(1, mode="drop"))


def stratified_estimate(
    y, slot, counts, volume, n_nonfinite, diagnostics: bool = True
) -> tuple[Estimate, jax.Array]:
    r"""The stratified estimate from values `y` `(n, ...)` laid out stratum by stratum (§4.2).

    Stratum $h$ of relative volume $v_h$ (`volume`: one scalar for equal strata,
    or `(H,)`) holds $n_h$ = `counts[h]` of the samples (`slot` gives each
    sample's stratum, sorted); with $\bar y_h$ and $s_h^2$ its sample mean and
    unbiased variance,
    $$\hat I = \sum_h v_h \bar y_h,\qquad \hat V = \sum_h v_h^2\, s_h^2 / n_h.$$
    Strata with fewer than two samples contribute no variance. When the
    contributions have a power-law tail the variance is at least their i.i.d.
    one (`bounded_variance`: pairs in strata miss a singularity). Without
    `diagnostics` the largest values are not sought: no Pareto $\hat k$ (NaN)
    and no such bound, for rounds whose variance is not reported.

    **Returns:** the `Estimate` and the per-stratum variances $s_h^2$ `(H, ...)`.
    """
    h = counts.shape[0]
    cnt = counts.astype(y.dtype)
    shape = (h,) + (1,) * (y.ndim - 1)
    seg = lambda a: jax.ops.segment_sum(a, slot, h, indices_are_sorted=True)  # noqa: E731
    per_stratum = jnp.reshape(jnp.maximum(cnt, 1.0), shape)
    mean_h = seg(y) / per_stratum
    var_h = seg((y - mean_h[slot]) ** 2) / jnp.reshape(jnp.maximum(cnt - 1.0, 1.0), shape)
    if jnp.ndim(volume) == 0:  # equal strata: factor the volume out of the sums
        mean = volume * jnp.sum(mean_h, axis=0)
        variance = volume**2 * jnp.sum(var_h / per_stratum, axis=0)
    else:
        v = jnp.reshape(volume, shape)
        mean = jnp.sum(v * mean_h, axis=0)
        variance = jnp.sum(v**2 * var_h / per_stratum, axis=0)
    # The diagnostics are of the values y = f/p themselves: weighted by an uneven allocation
    # (VEGAS+) the contributions' spread would reflect the allocation, not a heavy tail.
    n = jnp.asarray(y.shape[0], jnp.int32)
    if not diagnostics:
        fields = diagnosed(mean, variance, n, n_nonfinite, tail_sums(y))
        fields["pareto_k"] = jnp.full_like(fields["pareto_k"], jnp.nan)
        return Estimate(**fields), var_h
    tail = tail_of(y)
    # (For adaptive rounds `combine` flags the combination only when conservative rounds
    # carry most of its weight: a young grid's round on a peak often is, and says little.)
    variance, conservative = bounded_variance(variance, mean, tail)
    est = Estimate(**diagnosed(mean, variance, n, n_nonfinite, tail, conservative))
    return est, var_h
