r"""`expectation`: moments of an unnormalised density on a box, and its normalising constant.

For $\pi = e^{\ell}$ known up to a constant (a Bayesian posterior) on a box,
points $x_i \sim q$ from a density fitted to $\pi$ and weights
$w_i = \pi(x_i)/q(x_i)$ give the self-normalised (ratio) estimator
$\hat R = \sum_i w_i g(x_i) / \sum_i w_i$ of $E_\pi[g]$, $\hat Z = \bar w$ of
$\int\pi$, and by the delta method $\mathrm{Var}(\hat R) \approx
\mathrm{Var}(\bar z)/\hat Z^2$ with residuals $z_i = w_i (g(x_i) - \hat R)$
(Owen, *Monte Carlo theory, methods and examples*, §9.2). For points stratified
over a VEGAS+ map's hypercubes, $\hat Z$, the numerator and $\mathrm{Var}(\bar z)$
are stratified sums (the combined ratio estimator of survey sampling). Weights
are scaled by $e^{-c}$, $c = \max_i \log w_i$, so log densities of $-1000$
neither underflow nor overflow, and the evidence is also given as $\log\int\pi$.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from ._checks import (
    MAX_COUNT,
    check_bounds,
    check_choice,
    check_count,
    check_flag,
    check_key,
    is_concrete,
)
from ._compiled import release_if_crowded
from ._diagnostics import rounding_floor, warn_if_unreliable
from ._fit._vegas import strata_per_axis, stratified_unit_points
from ._integrand import bind, evaluate
from ._posterior_fit import PILOT, Fitted, Plan, fit, log_pi, plan_for, weights_of
from ._stats import Estimate, estimate_fields, estimate_iid, stratified_estimate
from ._unbounded import axis_kinds, map_expectation
from .fit import VegasPlus


METHODS = ("auto", "grid", "mixture")
MIN_N = 4096


class Expectation(Estimate):
    r"""What `expectation` returns: an `Estimate` of $E_\pi[g]$ and of the evidence $\int\pi$.

    `mean` has `g`'s output shape, `variance` is the delta-method variance of
    the ratio estimator, `n` counts the evaluations of the log density (fitting
    included), `n_nonfinite` the final points whose weight or `g` was not
    finite (weight zero). The diagnostics, the same for every component, are
    those of the weights $w_i = \pi(x_i)/q(x_i)$: `ess` is Kish's effective
    sample size $(\sum w_i)^2/\sum w_i^2$, `n_nonzero` counts non-zero
    weights, `pareto_k` is the Pareto $\hat k$ of their upper tail (PSIS).

    **Fields** (on top of `Estimate`'s):

    - `norm`: an `Estimate` of $\int\pi$, the evidence (marginal likelihood). Where the
      weights read a power-law tail its error bar is their i.i.d. bound, an upper bound
      (`norm.conservative`, flagged on `norm` alone: the mean's error bar is its own).
      It underflows to 0 when $\log\int\pi$ is below about $-87$ in float32
      ($-708$ in float64): read `log_norm` then.
    - `log_norm`: an `Estimate` of $\log\int\pi$, with the delta-method
      variance $\mathrm{Var}(\hat Z)/\hat Z^2$; always representable.
    - `pilot`: `(2,)`, $n\,\mathrm{Var}(\hat Z)/\hat Z^2$ in the last fitting
      round of the grid and of the mixture (`inf` if not fitted).
    - `method`: the density the final points came from, `"grid"` or
      `"mixture"` (`"auto"` when the choice was traced under `jit`).
    """

    norm: Estimate
    log_norm: Estimate
    pilot: jax.Array
    method: str = eqx.field(static=True)

    def __repr__(self) -> str:
        """`Estimate`'s repr (the numbers), then the evidence estimates by their own repr."""
        if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(self)):
            return eqx.Module.__repr__(self)
        head = repr(Estimate(**estimate_fields(self)))
        pilot = ", ".join(f"{float(v):.3g}" for v in jnp.ravel(self.pilot))
        return (
            f"{type(self).__name__}({head[head.index('(') + 1 : -1]}, norm={self.norm!r}, "
            f"log_norm={self.log_norm!r}, pilot=[{pilot}], method={self.method!r})"
        )


def expectation(
    key: jax.Array,
    g: Callable,
    log_density: Callable,
    lo: Any,
    hi: Any,
    *,
    n: int,
    method: str = "auto",
    args: Any = None,
    batched: bool = False,
) -> Expectation:
    r"""Expectation $E_\pi[g] = \int g\,\pi / \int\pi$ under an unnormalised density on a box.

    $\pi = \exp(\text{log\_density})$ need not be normalised (a posterior:
    log-likelihood plus log-prior); its integral, the evidence, comes with the
    result. As vegas's `PDFIntegrator`: self-normalised importance sampling
    from a density $q$ fitted to $\pi$, $\hat R = \sum_i w_i g(x_i)/\sum_i w_i$
    with $w_i = \pi(x_i)/q(x_i)$, and the delta-method variance
    $\mathrm{Var}(\hat R) \approx \mathrm{Var}(\overline{w(g - \hat R)})/\hat Z^2$.
    How $q$ is fitted:

    1. $\log\pi$ at 256 uniform points sets the scale; a VEGAS+ grid
       (`jaxmc.fit.VegasPlus`) adapts to $\pi$ for up to ten rounds on at most
       a quarter of the budget.
    2. `"mixture"`: 16 diagonal Gaussians fitted by EM
       (`GaussianMixture.from_samples`) to the grid's weighted samples, then
       twice to weighted samples of themselves (three rounds of about $n/40$
       points). Each round's $q$ is the mixture with its scales widened by 1.4
       plus a broad Gaussian of weight 0.1 (three times the samples' spread):
       $q$'s tails are heavier than $\pi$'s, so the weights stay bounded.
       Gaussians along a ridge follow correlations a separable grid cannot.
    3. `"grid"`: the trained grid, frozen, the final points stratified over
       its hypercubes as in its last round ($\hat Z$, the numerator and the
       variance are stratified sums). Best on near-separable densities; on
       strongly correlated ones the grid's weights are heavy-tailed.
    4. `"auto"` (default) fits both and keeps the one whose last fitting
       round had the lower relative variance of $\hat Z$ per evaluation
       (`pilot`); the grid's read at most at the pessimistic bound the
       scatter of its last rounds' estimates gives, as `integrate`'s `auto`
       reads a trained grid (one unresolved hypercube inflates a round's own
       variance).

    The fitting rounds' evaluations count in `n` but not in the estimate,
    which uses fresh points from the frozen density (unbiased up to the ratio
    estimator's $O(1/n)$ bias). `jax.grad` with respect to `args` holds the
    fitted density fixed: derivatives flow through the weights and `g`.

    **Arguments:**

    - `key`: a PRNG key.
    - `g`: the function to average, for one point (`g(x)`, or `g(x, args)`);
      any fixed output shape, e.g. `jnp.concatenate([x, jnp.outer(x, x).ravel()])`
      for means and second moments. Evaluated at the final points only.
    - `log_density`: $\log\pi$ for one point (or `log_density(x, args)`), a
      scalar; $-\infty$ where $\pi = 0$; $\pi$ is zero outside the box.
    - `lo`, `hi`: the box (scalars or shape `(d,)`); limits may be infinite, mapped onto
      finite ones as by `integrate` (a map fitted to $\pi$; its evaluations count in `n`).
    - `n`: evaluations of `log_density` in all (a static int >= 4096).
    - `method`: `"auto"`, `"mixture"` or `"grid"` (above).
    - `args`: a pytree passed to `g` and `log_density` as their second
      argument; new values of the same shapes reuse the compiled code.
    - `batched`: `g` and `log_density` take the whole `(m, d)` batch.

    **Returns:** an `Expectation`: an `Estimate` of $E_\pi[g]$ with `norm`
    and `log_norm` (`Estimate`s of $\int\pi$ and $\log\int\pi$). Outside
    `jit`, diagnostics saying the error bar cannot be trusted (a few weights
    carry the mean) warn with `jaxmc.ReliabilityWarning`. The final points are
    evaluated in one batch: memory grows with `n`.

    !!! Example

        ```python
        log_post = lambda x: -0.5 * jnp.sum(((x - 0.3) / 0.05) ** 2) - 1000.0
        moments = lambda x: jnp.concatenate([x, jnp.outer(x, x).ravel()])
        est = jaxmc.expectation(jax.random.key(0), moments, log_post, [0.0] * 3, [1.0] * 3, n=100_000)
        print(est.mean[:3], est.stderr[:3], est.log_norm.mean)
        ```
    """
    key = check_key(key)
    g, log_density = bind(g, args, "g"), bind(log_density, args, "log_density")
    kinds = axis_kinds(lo, hi)
    lo, hi = check_bounds(lo, hi, infinite=True)
    n = check_count(n, "n", minimum=MIN_N, maximum=MAX_COUNT)
    method = check_choice(method, "method", METHODS)
    batched = check_flag(batched, "batched")
    release_if_crowded(key, lo, hi, g, log_density)
    _check_outputs(g, log_density, lo, batched)
    probes = 0
    if kinds is not None:
        key, key_maps = jax.random.split(key)
        g, log_density, lo, hi, probes = map_expectation(
            key_maps, g, log_density, lo, hi, kinds=kinds, n=n, minimum=MIN_N, batched=batched)
        n -= probes
    plan = plan_for(n, method)
    key_fit, key_final = jax.random.split(key)
    fitted = fit(key_fit, log_density, lo, hi, plan=plan, batched=batched)
    fitted = jax.lax.stop_gradient(fitted)  # a fixed design: derivatives flow through the weights
    run = lambda m: _final(key_final, g, log_density, fitted, plan=plan, batched=batched, method=m)  # noqa: E731
    if method == "auto":
        choice = jnp.argmin(fitted.relative_variance)  # ties (both blind): the grid
        if is_concrete(choice):
            method = ("grid", "mixture")[int(choice)]
            fields = run(method)
        else:  # chosen under jit: both are compiled, one runs
            fields = jax.lax.cond(choice == 0, lambda: run("grid"), lambda: run("mixture"))
    else:
        fields = run(method)
    est = Expectation(**fields, pilot=fitted.relative_variance, method=method)
    if probes:  # (the map's fit counts in `n`, the evidence's too)
        est = eqx.tree_at(lambda e: (e.n, e.norm.n, e.log_norm.n), est,
                          (est.n + probes, est.norm.n + probes, est.log_norm.n + probes))
    warn_if_unreliable(est, "expectation")
    return est


def _check_outputs(g, log_density, lo, batched) -> None:
    """Trace-time checks of both functions; `log_density` gives one scalar per point."""
    points = jnp.zeros((2,) + lo.shape, lo.dtype)
    shape = jax.eval_shape(lambda x: evaluate(log_density, x, batched, "log_density"), points).shape
    if shape != (2,):
        raise ValueError(
            "`log_density` must return one scalar per point, got shape "
            f"{shape if batched else shape[1:]} for {'a batch of 2 points' if batched else 'a point'}."
        )
    jax.eval_shape(lambda x: evaluate(g, x, batched, "g"), points)


def _final_draw(key, fitted: Fitted, plan: Plan, method: str):
    """The final points `x`, $\\log q(x)$, and their strata `(slot, counts, volume)` or `None`."""
    grid = fitted.grid
    if method == "mixture":
        x, _ = fitted.mixture.sample(key, plan.final)
        # In chunks: the mixture's density holds (points, components, d) arrays.
        return x, jax.lax.map(fitted.mixture.log_pdf, x, batch_size=1 << 14), None
    # The training's last allocation, repeated: `final // block` copies of each cube's
    # count, the remainder spread in proportion (cumulative rounding keeps the total).
    copies, rest = divmod(plan.final, plan.block)
    counts = fitted.counts
    cum = jnp.floor(jnp.cumsum(counts) * (rest / plan.block) + 0.5).astype(jnp.int32)
    counts = copies * counts + jnp.diff(jax.lax.cummax(cum).at[-1].set(rest), prepend=0)
    strata = strata_per_axis(grid.dim, plan.block, VegasPlus().max_strata)
    raw = jax.random.uniform(key, (plan.final, grid.dim), grid.lo.dtype)
    draw = stratified_unit_points(raw, counts, strata)
    x, log_q, _ = grid.map_with_bins(draw.u)
    x = x[:, 0] if grid.event_ndim == 0 else x
    return x, log_q, (draw.cube, counts, 1.0 / counts.shape[0])


def _design_moments(y: jax.Array, strata) -> tuple[jax.Array, jax.Array]:
    r"""Mean and its variance of values `y` `(m, k)` under the draw's design.

    i.i.d.: $\bar y$ and $s^2/m$; stratified (cube $h$ of volume $v$ holding
    $n_h$ points): $v\sum_h \bar y_h$ and $v^2 \sum_h s_h^2/n_h$ (§4.2).
    """
    if strata is None:
        m = y.shape[0]
        return jnp.mean(y, axis=0), jnp.var(y, axis=0, ddof=1) / m
    slot, counts, volume = strata
    h = counts.shape[0]
    cnt = counts.astype(y.dtype)[:, None]
    mean_h = jax.ops.segment_sum(y, slot, h, indices_are_sorted=True) / cnt
    dev2 = jax.ops.segment_sum((y - mean_h[slot]) ** 2, slot, h, indices_are_sorted=True)
    var_h = dev2 / jnp.maximum(cnt - 1, 1)
    return volume * jnp.sum(mean_h, axis=0), volume**2 * jnp.sum(var_h / cnt, axis=0)


@eqx.filter_jit
def _final(key, g, log_density, fitted: Fitted, *, plan: Plan, batched: bool, method: str):
    """The ratio estimator on the final points: `Expectation`'s fields (but `method`)."""
    dtype = fitted.grid.lo.dtype
    x, log_q, strata = _final_draw(key, fitted, plan, method)
    m = plan.final
    w, top, bad = weights_of(log_pi(log_density, x, batched, dtype), log_q)
    gx = evaluate(g, x, batched, "g").astype(dtype)
    shape = gx.shape[1:]
    gx = jnp.reshape(gx, (m, -1))
    # A g that is not finite where the weight is zero carries no mass.
    g_ok = jnp.isfinite(gx)
    bad = bad | ((w > 0) & ~jnp.all(g_ok, axis=1))
    w = jnp.where(bad, 0.0, w)
    gx = jnp.where(g_ok & (w > 0)[:, None], gx, 0.0)

    # The weights' estimate carries the evidence and the diagnostics of the weights.
    if strata is None:
        weights = estimate_iid(w[:, None], bad)
    else:
        weights = stratified_estimate(w[:, None], *strata, jnp.sum(bad, dtype=jnp.int32))[0]
    z_hat = weights.mean[0]
    seen = z_hat > 0
    safe_z = jnp.where(seen, z_hat, 1.0)
    numerator, _ = _design_moments(w[:, None] * gx, strata)
    ratio = jnp.where(seen, numerator / safe_z, jnp.nan)
    _, residual_variance = _design_moments(w[:, None] * (gx - jnp.where(seen, ratio, 0.0)), strata)
    # The mean itself is rounded at the level of E_pi|g|: never claim less.
    floor = rounding_floor(dtype) * _design_moments(w[:, None] * jnp.abs(gx), strata)[0] / safe_z
    variance = jnp.where(seen, jnp.maximum(residual_variance / safe_z**2, floor**2), jnp.inf)

    n = jnp.asarray(PILOT + (plan.rounds + plan.mixture_rounds) * plan.block + m, jnp.int32)
    diagnostics = {k: getattr(weights, k)[0] for k in ("ess", "n_nonzero", "pareto_k")}
    common = dict(n=n, n_nonfinite=weights.n_nonfinite, **diagnostics)
    evidence_bound = weights.conservative[0]
    relative = jnp.where(seen, weights.variance[0] / safe_z**2, jnp.inf)
    log_z = jnp.where(seen, jnp.log(safe_z) + top, -jnp.inf)
    norm = jnp.exp(log_z)
    per_component = {k: jnp.broadcast_to(v, shape) for k, v in diagnostics.items()}
    return dict(
        common,
        mean=jnp.reshape(ratio, shape),
        variance=jnp.reshape(variance, shape),
        **per_component,
        # (Where the weights' stratified variance gave way to their i.i.d. bound, the
        # evidence's error bar is that bound, and says so; the ratio's is its own.)
        norm=Estimate(mean=norm, variance=norm**2 * relative, conservative=evidence_bound,
                      **common),
        log_norm=Estimate(mean=log_z, variance=relative, conservative=evidence_bound,
                          **common),
    )
