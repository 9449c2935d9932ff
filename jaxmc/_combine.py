r"""`combine`: estimates of one integral merged by inverse-variance weights (`Combined`)."""

from __future__ import annotations

import functools
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.scipy.special import gammaincc

from ._diagnostics import MIN_ESS
from ._format import iteration_tables
from ._stats import Estimate, estimate_fields


class Combined(Estimate):
    r"""Inverse-variance weighted combination of independent estimates.

    On top of `Estimate`'s fields: `chi2_dof`, the $\chi^2$ of the parts about
    the combined mean per degree of freedom (near 1 when the parts agree within
    their error bars), `q`, the probability that a $\chi^2$ variable with that
    many degrees of freedom is at least as large (tiny $q$ means the parts
    disagree, e.g. an adaptive density missed a peak), and `parts`, the inputs
    stacked along a leading axis, and `sequential`, whether they were weighted
    as successive adaptive rounds. Its `ess` and `n_nonzero` are the parts'
    sums, its `pareto_k` the parts' average weighted as their means are, it
    is `conservative` when parts that are carry over half the weight, and its
    `dof` is Welch and Satterthwaite's $(\sum_i a_i V_i)^2 / \sum_i (a_i V_i)^2/\nu_i$
    for the pooled variance $\sum_i a_i V_i$ (infinite when every part's is).
    """

    chi2_dof: jax.Array
    q: jax.Array
    parts: Estimate
    sequential: bool = eqx.field(static=True, default=False, kw_only=True)

    def summary(self) -> str:
        """The parts (iterations) as a text table, like vegas's `summary()`.

        One row per part: `itn`, its estimate, the weighted average of parts 1
        to `itn` (`combine`: the last row's is this one) and that average's
        `chi2/dof` and `Q`, numbers in the compact notation (`0.9977(42)`). An
        array-valued estimate gets one table per component, headed by its
        index, with the component's own `chi2/dof` and `Q` (`chi2_dof` here
        sums over components). Outside `jit` only.
        """
        return iteration_tables(self, functools.partial(combine, sequential=self.sequential))


def _stack(estimates: Estimate | Sequence[Estimate]) -> Estimate:
    if isinstance(estimates, Estimate):
        parts = estimates
        if jnp.ndim(parts.n) != 1:
            raise ValueError(
                "`estimates` given as one Estimate must be stacked along a leading axis "
                f"(e.g. from jax.vmap), got n of shape {jnp.shape(parts.n)}."
            )
        return _plain(parts)
    estimates = list(estimates)
    if not estimates or not all(isinstance(e, Estimate) for e in estimates):
        raise TypeError("`estimates` must be a non-empty sequence of Estimate or a stacked Estimate.")
    plain = [_plain(e) for e in estimates]
    return jax.tree.map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *plain)


def _plain(e: Estimate) -> Estimate:
    return Estimate(**estimate_fields(e))


def combine(estimates: Estimate | Sequence[Estimate], *, sequential: bool = False) -> Combined:
    r"""Combine independent estimates of the same integral by inverse-variance weights.

    With $w_i = 1/V_i$: $\bar I = \sum_i w_i I_i / \sum_i w_i$, $V = 1/\sum_i w_i$,
    and $\chi^2 = \sum_i (I_i - \bar I)^2 / V_i$ with $k - 1$ degrees of freedom
    ($k$ parts), as vegas reports across its iterations. For array-valued
    estimates each component is combined on its own and the $\chi^2$ is summed
    over components (with $(k-1)\cdot$size degrees of freedom).

    `sequential=True` is for the rounds of an adaptive method (`jaxmc.fit.adapt`
    uses it). A round's own variance moves with its estimate when $f/p$ is
    skewed (a round whose density starved a region reports both a low value and
    a small variance), so weights $1/V_i$ favour the low rounds and bias the mean
    low, by many of its own standard errors. Round $i$ is weighted instead by the
    inverse variance it was expected to have from the last round before it with a
    measured one, $w_i =
    n_i/(n_{j(i)} V_{j(i)})$ ($n$ its evaluations: $1/V_{j(i)}$ for rounds of one
    size), a figure fixed before round $i$ drew its samples, so that $\sum_i w_i (I_i - I)$ is a
    martingale with mean zero (the first measured round, with nothing before
    it, is weighted by its own variance). What bias is left comes from dividing
    by $\sum_i w_i$, and is far smaller than that of weights $1/V_i$. Then
    $V = \sum_i w_i^2 V_i / (\sum_i w_i)^2$.

    Parts with zero variance need a rule, since $1/V$ is infinite:

    - zero variance and a non-zero mean (every sample of $f/p$ equal: an exact
      zero-variance density) is exact, and the exact parts get all the weight;
    - zero variance and zero mean (every sample zero: e.g. an adaptive round
      whose density missed the integrand's peak) carries no information and
      gets no weight, rather than swallowing the others. If every part is like
      that, the result is 0 with variance 0.

    A part with an effective sample size below 10 (`ess`: a handful of values
    carried its mean, so its variance says nothing) gets no weight either, unless
    no part is better measured.

    Only the parts with finite, positive variance enter the $\chi^2$, and the
    degrees of freedom count them (one fewer than their number); a part with an
    infinite or NaN variance gets no weight (if no part has any, the result is
    NaN with infinite variance).

    **Arguments:**

    - `estimates`: a sequence of `Estimate`s, or one `Estimate` stacked along a
      leading axis.
    - `sequential`: the parts are successive rounds of an adaptive method, each
      drawn from a density the earlier ones shaped (weights from the round before).

    **Returns:** a `Combined`.
    """
    parts = _stack(estimates)
    var = parts.variance
    flat = var <= 0
    empty = flat & (parts.mean == 0)
    exact = flat & ~empty
    any_exact = jnp.any(exact, axis=0)
    measured = (var > 0) & jnp.isfinite(var)
    # A part whose mean a handful of values carried has a variance that means nothing (a
    # round that grazed a peak's far tail reports a tiny mean with a tiny error bar); while
    # any part is better measured, it gets no weight and lends none.
    # Per-part figures as arrays like the variances (hand-built parts may carry the scalar
    # defaults of the diagnostics).
    ess, n, n_nonzero, part_k, bounded = (
        _per_part(a, var)
        for a in (parts.ess, parts.n, parts.n_nonzero, parts.pareto_k, parts.conservative)
    )
    grazed = ess < jnp.minimum(MIN_ESS, n / 4)  # (NaN, unknown, is not grazed)
    trusted = measured & ~grazed
    measured = jnp.where(jnp.any(trusted, axis=0), trusted, measured)
    safe_var = jnp.where(measured, var, 1.0)
    if sequential:
        # The variance a part of n_i evaluations was expected to have, from the variance
        # per evaluation the part before it measured: n_j V_j / n_i.
        size = jnp.where(n > 0, n, 1).astype(var.dtype)
        weighed_by = _previous_measured(safe_var * size, measured) / size
    else:
        weighed_by = safe_var
    # Exact parts share all the weight among themselves; otherwise inverse variances
    # (scaled by the largest: weights of 1e280 would overflow when squared).
    w = jnp.where(any_exact, exact, jnp.where(measured, 1.0 / weighed_by, 0.0))
    w = w.astype(var.dtype)
    w = w / jnp.where(jnp.any(w > 0, axis=0), jnp.max(w, axis=0), 1.0)
    wsum = jnp.sum(w, axis=0)
    informative = wsum > 0
    safe_wsum = jnp.where(informative, wsum, 1.0)
    # No weight anywhere: all parts empty gives 0 +- 0; otherwise nothing is known.
    all_empty = jnp.all(empty, axis=0)
    unknown_mean = jnp.where(all_empty, 0.0, jnp.nan)
    mean = jnp.where(informative, jnp.sum(w * parts.mean, axis=0) / safe_wsum, unknown_mean)
    unknown_var = jnp.where(all_empty, 0.0, jnp.inf)
    term = w**2 * safe_var  # each part's share of the pooled variance, times (sum w)^2
    pooled = jnp.sum(term, axis=0) / safe_wsum**2  # 1 / sum(w) for w = 1/V
    variance = jnp.where(any_exact, 0.0, jnp.where(informative, pooled, unknown_var))
    chi2_terms = jnp.where(measured, (parts.mean - mean) ** 2 / jnp.where(measured, var, 1.0), 0.0)
    chi2 = jnp.sum(chi2_terms)
    dof = jnp.sum(jnp.maximum(jnp.sum(measured, axis=0) - 1, 0)).astype(var.dtype)
    has_dof = dof > 0
    safe_dof = jnp.where(has_dof, dof, 1.0)
    chi2_dof = jnp.where(has_dof, chi2 / safe_dof, 0.0)
    q = jnp.where(has_dof, gammaincc(safe_dof / 2.0, chi2 / 2.0), 1.0)
    # Welch-Satterthwaite: the pooled variance sum_i a_i V_i (a_i = w_i^2 / (sum w)^2) has
    # (sum a_i V_i)^2 / sum_i (a_i V_i)^2 / nu_i degrees of freedom (infinite for normal parts).
    part_dof = _per_part(parts.dof, var)
    spread = jnp.sum(jnp.where(jnp.isfinite(part_dof) & (term > 0),
                               term**2 / jnp.where(part_dof > 0, part_dof, 1.0), 0.0), axis=0)
    total = jnp.sum(term, axis=0)
    satterthwaite = jnp.where(spread > 0, total**2 / jnp.where(spread > 0, spread, 1.0), jnp.inf)
    # Diagnostics: effective sizes and non-zero counts add up; the tail shape is the
    # weight-averaged one of the parts that carry weight.
    share = w / safe_wsum
    weighted_k = jnp.sum(jnp.where(share > 0, share * part_k, 0.0), axis=0)
    known = jnp.all(n_nonzero >= 0, axis=0)
    # Conservative when the parts that carry most of the weight are (a young grid's round
    # may be, on a peak, without saying much of the combination).
    return Combined(
        mean=mean,
        variance=variance,
        # (Counts keep their dtype: with x64 on, a sum would widen int32 to int64.)
        n=jnp.sum(parts.n, dtype=jnp.result_type(parts.n)),
        n_nonfinite=jnp.sum(parts.n_nonfinite, dtype=jnp.result_type(parts.n_nonfinite)),
        ess=jnp.sum(ess, axis=0),
        n_nonzero=jnp.where(known, jnp.sum(n_nonzero, axis=0, dtype=jnp.result_type(n_nonzero)), -1),
        pareto_k=jnp.where(informative, weighted_k, jnp.nan),
        conservative=jnp.sum(jnp.where(bounded, share, 0.0), axis=0) > 0.5,
        dof=jnp.where(informative & ~any_exact, satterthwaite, jnp.inf),
        chi2_dof=chi2_dof,
        q=q,
        parts=parts,
        sequential=bool(sequential),
    )


def _previous_measured(var: jax.Array, measured: jax.Array) -> jax.Array:
    """For each part (axis 0), the variance of the last earlier measured part, or its own
    when no earlier part was measured."""
    k = var.shape[0]
    index = jnp.reshape(jnp.arange(k), (k,) + (1,) * (var.ndim - 1))
    last = jax.lax.cummax(jnp.where(measured, index, -1), axis=0)  # last measured at or before i
    before = jnp.concatenate([jnp.full_like(last[:1], -1), last[:-1]], axis=0)
    earlier = jnp.take_along_axis(var, jnp.maximum(before, 0), axis=0)
    return jnp.where(before >= 0, earlier, var)


def _per_part(a: jax.Array, like: jax.Array) -> jax.Array:
    """`a`, one value per part (or per part and component), broadcast to `like`'s shape."""
    return jnp.broadcast_to(jnp.reshape(a, jnp.shape(a) + (1,) * (jnp.ndim(like) - jnp.ndim(a))),
                            jnp.shape(like))

