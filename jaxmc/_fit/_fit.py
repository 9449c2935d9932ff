r"""Fit a proposal to an integrand by minimising the importance estimator's variance.

The importance estimator $f(X)/p(X)$, $X \sim p_\theta$, has variance
$M_2(\theta) - I^2$ with second moment $M_2(\theta) = E_p[(f/p)^2] = \int f^2/p$,
so minimising $M_2$ minimises the variance. `fit` hands a sample-average
approximation of $\log M_2$ (or of another objective) to an optimistix
minimiser, over the proposal's parameters — its inexact-array leaves apart from
the box bounds (`eqx.partition`/`eqx.combine`). By default the jaxmc proposals
are instead fitted to the importance-weighted samples of a few VEGAS rounds
(`_default_fit`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx

from .. import _random
from .._box import log_volume, to_box
from .._checks import MAX_COUNT, check_callable, check_choice, check_count, check_key
from .._integrand import bind
from ..proposals import check_proposal, weighted_draw
from ._default_fit import default_fit, has_default_fit
from ._objectives import OBJECTIVES, log_abs, objective_loss
from ._rule import Integrand
from ._solvers import check_solver, minimise, run_steps, split_parameters


class FitResult(eqx.Module):
    """What `fit` returns.

    **Fields:**

    - `proposal`: the fitted proposal (same type as the input).
    - `loss`: the objective at the fitted parameters, on the fit's samples (for
      `"variance"` the log of the estimated second moment $\\log E_p[(f/p)^2]$;
      for `"chi2"` $\\log(1 + \\chi^2)$; for `"kl"`/`"reverse_kl"` the divergence).
    - `steps`: the number of solver steps taken.
    - `result`: an `optimistix.RESULTS` item (`successful`, or why it stopped).
    - `losses`: the loss at every step for `resample=True` (shape `(max_steps,)`),
      or a flow's divergence at every step of its default fit, else `None`.
    """

    proposal: Any
    loss: jax.Array
    steps: jax.Array
    result: optx.RESULTS
    losses: jax.Array | None = None


def _check_defensive(defensive) -> float:
    if not (isinstance(defensive, (int, float)) and 0 <= defensive < 1):
        raise ValueError(f"`defensive` must be a number in [0, 1), got {defensive!r}.")
    return defensive


def _defensive_count(defensive, n: int, objective: str) -> int:
    if objective == "reverse_kl" or defensive == 0:
        return 0
    n_def = int(round(defensive * n))
    if not 1 <= n_def < n:
        raise ValueError(
            f"`n` = {n} is too small for `defensive` = {defensive}: need at least one "
            "defensive and one proposal sample."
        )
    return n_def


def _defensive_draw(prop, key, n: int, n_def: int, eps: float):
    r"""Draw from $m = (1-\epsilon) p_\theta + \epsilon\,U$ stratified: `n - n_def` from $p_\theta$ (moving
    with $\theta$), `n_def` uniform on the box (fixed). Returns `(x, log p, log m, weights)`;
    $\sum_i w_i g(x_i)/m(x_i)$ estimates $\int g$ (balance-heuristic MIS).
    """
    key_p, key_u = jax.random.split(key)
    x_p, _, w_p = weighted_draw(prop, key_p, n - n_def)
    lo, hi = jnp.asarray(prop.lo), jnp.asarray(prop.hi)
    u = _random.uniform(key_u, (n_def,) + lo.shape, lo.dtype)
    x_u = to_box(u, lo, hi)
    x = jnp.concatenate([x_p, x_u], axis=0)
    log_p = prop.log_pdf(x)
    log_vol = log_volume(lo, hi)
    log_m = jnp.logaddexp(jnp.log1p(-eps) + log_p, jnp.log(eps) - log_vol)
    w = jnp.concatenate([(1 - eps) * w_p, jnp.full((n_def,), eps / n_def, w_p.dtype)])
    return x, log_p, log_m, w



def fit(
    key: jax.Array,
    f: Callable,
    proposal: Any,
    n: int,
    *,
    solver: optx.AbstractMinimiser | None = None,
    objective: str = "variance",
    max_steps: int = 256,
    batched: bool = False,
    reuse: bool = False,
    resample: bool | None = None,
    steps_per_batch: int = 1,
    filter_spec: Any = None,
    defensive: float = 0.1,
    args: Any = None,
) -> FitResult:
    r"""Fit `proposal` to `f` by minimising the importance estimator's variance.

    **Default: fit to VEGAS's weighted samples.** With no `solver` and the
    default `objective`, `reuse`, `resample` and `filter_spec`, the jaxmc
    proposals are not fitted by a gradient solver: a sample average of the
    variance is flat where the proposal puts no samples, so from a start that
    barely sees a narrow peak the solver drifts instead of finding it. Instead
    $R$ = `min(max_steps, 10)` rounds of `n` points of the VEGAS rule
    (`jaxmc.fit.Vegas`) on a 64-bin `Grid` find where $|f|$ is, and the
    proposal is fitted to the last round's samples $x_i \sim q$ with weights
    $w_i \propto |f(x_i)|/q(x_i)$ by minimising the forward divergence
    $$D(p_f \| p_\theta) = \text{const} - \textstyle\sum_i w_i \log p_\theta(x_i),
    \qquad p_f = |f|/I,$$
    whose minimiser over all densities is $p_f$, the zero-variance density
    (adaptive importance sampling as in population Monte Carlo, Cappé et al.
    2008, and neural importance sampling):

    - `Grid`: the $R$ VEGAS rounds are run on the proposal itself (a gradient
      solver stalls on a grid's piecewise-constant density).
    - `Partition`: $R$ rounds of MISER-like growth (`jaxmc.fit.PartitionGrowth`)
      instead, when `n >= 4 * max_cells` (else the gradient fit below).
    - `GaussianMixture`, `PiecewiseLinear`: expectation-maximisation on the
      weighted samples (`GaussianMixture.from_samples`,
      `PiecewiseLinear.from_samples`); the starting parameters are not used.
    - `Flow`: `max_steps` steps of Adam (learning rate $10^{-2}$) on
      $D(p_f \| p_\theta)$, each on a fresh batch of `n` points from the final
      grid (positive on the whole box, so no region is starved); `losses`
      holds the divergence at every step.
    - `Mixture` (of these, or of parameterless densities such as `Uniform`):
      each component as it would be fitted alone; fixed weights stay.

    `steps` is then $R$ (plus `max_steps` for a flow) and `loss` is the fitted
    proposal's $\log E_p[(f/p)^2]$ on the last round's samples, reweighted.
    Every other case (another proposal type, an explicit `solver`, or any of
    those options, or `steps_per_batch` > 1) is the gradient fit that follows;
    `defensive` applies to it alone.

    **Gradient fit.** The objective is the log of the second moment
    $$L(\theta) = \log \sum_i w_i \frac{f(x_i)^2}{p_\theta(x_i)^2},\qquad
    x_i = T_\theta(u_i),$$
    a sample average over `n` reparameterised draws with the base randomness
    $u_i$ fixed by `key` (the optimistix solver's `args`; by default a share
    `defensive` of them uniform on the box, see below), so $L$ is a
    deterministic, differentiable function of $\theta$ — what BFGS's line
    search assumes. It is evaluated with `logsumexp` in log space, so it is
    scale-free and does not overflow. Its minimiser is that of the variance
    $E_p[(f/p)^2] - I^2$.

    Other objectives (neural importance sampling, Müller et al. 2019, with
    $p_f = |f|/I$):

    - `"chi2"`: Pearson $\chi^2(p_f \| p) = E_p[(f/p)^2]/I^2 - 1$ (reported as
      $\log(1 + \chi^2)$); same minimiser as the variance, scale-normalised.
    - `"kl"`: $D_{KL}(p_f \| p_\theta)$, estimated on `n` samples drawn once from
      the initial proposal $q$ with weights $|f|/q$ (with `resample=True`:
      redrawn from the current proposal for every batch of `steps_per_batch` steps).
    - `"reverse_kl"`: $D_{KL}(p_\theta \| p_f) = E_p[\log p - \log|f|] + \log I$
      (mode-seeking; $\log|f|$ floored at $e^{-70}$ times its maximum).

    With `reuse=True` the `n` samples are drawn once from the initial (frozen)
    proposal $q$ and `f` is evaluated once; the objective then reweights them
    ($E_p[f^2/p^2] = E_q[f^2/(p\,q)]$) at every step — for expensive integrands
    (`fit_on_samples` does this for samples you already have).

    **Arguments:**

    - `key`: a PRNG key (fixes the base samples).
    - `f`: the integrand, written for one point (or a batch with `batched=True`).
    - `proposal`: a jaxmc proposal (`GaussianMixture`, `Grid`, `Flow`,
      `Mixture`, or any equinox Module with `sample`/`log_pdf`).
    - `n`: samples in the objective (static int).
    - `solver`: any `optimistix.AbstractMinimiser`. Default: the fit to VEGAS's
      samples above for the jaxmc proposals; otherwise
      `optimistix.BFGS(rtol=1e-5, atol=1e-5)` (`optimistix.LBFGS` above 2000
      parameters), or for a `Flow` (or a proposal containing one, e.g. with
      `resample=True`) a stochastic one, as in neural importance sampling: Adam,
      `optimistix.OptaxMinimiser(optax.adam(3e-3), rtol=0, atol=0)`, run for
      exactly `max_steps` steps on fresh samples (`resample` defaults to `True`).
      With other stochastic solvers pass `resample=True` yourself.
    - `objective`: `"variance"` (default), `"chi2"`, `"kl"` or `"reverse_kl"`.
    - `max_steps`: solver step limit (with `resample=True`, the exact number). For
      the default fits above: `min(max_steps, 10)` rounds, and a flow's Adam steps.
    - `batched`: `f` takes a batch.
    - `reuse`: fit on one batch from the frozen initial proposal.
    - `resample`: run exactly `max_steps` solver steps on fresh base samples
      (key folded with the batch index); for stochastic optimisers. Default
      `None`: `True` for a `Flow` with the default solver (unless `reuse`),
      else `False`.
    - `steps_per_batch`: with `resample=True`, take this many solver steps on
      each batch before drawing the next (`max_steps` must be a multiple).
      For frozen samples (`"kl"`, or `reuse`) the batch is drawn from the
      proposal as it was at the batch's start, `f` is evaluated once, and the
      samples are reweighted at every step, which keeps the objective unbiased
      while the proposal moves: `max_steps / steps_per_batch` batches of `n`
      integrand evaluations in all, more optimisation per evaluation. For the
      reparameterised objectives the batch's base samples are reused, but the
      points move with the parameters, so `f` is evaluated at every step.
    - `filter_spec`: which leaves to optimise (default: inexact arrays except
      `lo`/`hi`, see `parameter_spec`).
    - `defensive`: the share $\epsilon$ of the reparameterised objective's
      samples drawn uniformly on the box (fixed) instead of from $p_\theta$; the
      objective then estimates $\int f^2/p_\theta$ by MIS over
      $m = (1-\epsilon)p_\theta + \epsilon U$. Without it a sample average over
      moving samples can "win" by moving every sample off the peak (where
      $f \approx 0$); the fixed uniform samples keep a starved peak expensive.
      For frozen samples (`"kl"`, `reuse`) with `resample=True` the same share
      of each batch is drawn uniformly, so regions the proposal has starved
      still get samples (and weights); one frozen batch (`resample=False`) gets
      none. `0` disables it; ignored for `"reverse_kl"`.
    - `args`: parameters of `f` (any pytree); if given, `f` is called as
      `f(x, args)` (see `jaxmc.integrate`).

    **Returns:** a `FitResult`. Solver failures (e.g. `max_steps` reached) are
    reported in `result`, not raised.

    `fit` is compiled once per integrand object `f`, proposal structure,
    solver and sizes (seconds for a `Flow`): fitting again with a new key,
    new starting parameters or new `args` of the same shapes reuses it; a new
    closure per call compiles anew.

    !!! Example

        ```python
        f = lambda x: jnp.exp(-jnp.sum((x - 0.5) ** 2) / 0.01)
        g = jaxmc.proposals.GaussianMixture(jax.random.key(1), jnp.zeros(2), jnp.ones(2), 4)
        res = jaxmc.fit.fit(jax.random.key(0), f, g, 2048)
        jaxmc.importance(jax.random.key(2), f, res.proposal, 10_000)
        ```
    """
    key = check_key(key)
    f = check_callable(f)
    proposal = check_proposal(proposal, methods=("sample", "log_pdf"))
    n = check_count(n, maximum=MAX_COUNT)
    max_steps = check_count(max_steps, "max_steps")
    objective = check_choice(objective, "objective", OBJECTIVES)
    steps_per_batch = check_count(steps_per_batch, "steps_per_batch")
    if max_steps % steps_per_batch:
        raise ValueError(
            f"`max_steps` = {max_steps} must be a multiple of `steps_per_batch` = {steps_per_batch}."
        )
    defensive = _check_defensive(defensive)
    # Any option of the gradient fit asks for it.
    plain = objective == "variance" and steps_per_batch == 1 and not (
        reuse or resample or filter_spec is not None
    )
    integrand = Integrand(bind(f, args), batched)
    if solver is None and plain and has_default_fit(proposal, n):
        return _default_fit(key, integrand, proposal, n, max_steps)
    params, static = split_parameters(proposal, filter_spec)
    default_solver = solver is None
    solver = check_solver(solver, proposal, params)
    if resample is None:
        # A stochastic default (the flows' Adam) gets fresh samples at every step, unless
        # the caller asked to fit on one reused batch.
        resample = default_solver and isinstance(solver, optx.OptaxMinimiser) and not reuse
    if steps_per_batch > 1 and not resample:
        raise ValueError("`steps_per_batch` > 1 needs `resample=True`.")
    frozen = reuse or objective == "kl"
    # One frozen batch gets no uniform share: maximising a weighted likelihood on a fixed
    # sample can put a spike on one heavily weighted uniform point (a mixture component
    # shrinks onto it and the objective runs to -inf). Fresh batches leave no such spike.
    n_def = 0 if frozen and not resample else _defensive_count(defensive, n, objective)
    return _gradient_fit(
        key, integrand, params, static, solver, n=n, n_def=n_def, defensive=defensive,
        objective=objective, frozen=frozen, resample=resample, max_steps=max_steps,
        steps_per_batch=steps_per_batch,
    )


# Both fits are compiled once per integrand object, proposal structure, solver and sizes:
# fitting again with a new key, starting parameters or `args` reuses the compiled code.


@eqx.filter_jit
def _default_fit(key, integrand, proposal, n, max_steps):
    fitted, loss, steps, losses = default_fit(key, integrand, proposal, n, max_steps)
    return FitResult(fitted, loss, steps, optx.RESULTS.successful, losses)


@eqx.filter_jit
def _gradient_fit(
    key, integrand, params, static, solver, *, n, n_def, defensive, objective, frozen, resample,
    max_steps, steps_per_batch,
):
    """The gradient fit of `fit` on the parameters `params` (the rest of the proposal in `static`)."""

    def draw_frozen(k, p):
        prop = eqx.combine(jax.lax.stop_gradient(p), static)
        if n_def == 0:
            x, log_q, w = weighted_draw(prop, k, n)
        else:
            x, _, log_q, w = _defensive_draw(prop, k, n, n_def, defensive)
        logf = log_abs(integrand(x))
        return x, jax.lax.stop_gradient(logf), jax.lax.stop_gradient(log_q), w

    if frozen:

        def loss(p, samples):
            x, logf, log_q, w = samples
            log_p = eqx.combine(p, static).log_pdf(x)
            return objective_loss(objective, logf, log_p, w, log_q)

        if resample:
            make_args = lambda i, p: draw_frozen(jax.random.fold_in(key, i), p)
        else:
            solver_args = draw_frozen(key, params)
    else:

        def loss(p, k):
            prop = eqx.combine(p, static)
            if n_def == 0:
                x, log_p, w = weighted_draw(prop, k, n)
                logf = log_abs(integrand(x))
                return objective_loss(objective, logf, log_p, w)
            x, log_p, log_m, w = _defensive_draw(prop, k, n, n_def, defensive)
            logf = log_abs(integrand(x))
            return objective_loss(objective, logf, log_p, w, log_m)

        make_args = lambda i, p: jax.random.fold_in(key, i)
        solver_args = key

    if resample:
        params, losses = run_steps(make_args, loss, solver, params, max_steps, steps_per_batch)
        final = loss(params, make_args(max_steps // steps_per_batch - 1, params))
        return FitResult(
            proposal=eqx.combine(params, static),
            loss=final,
            steps=jnp.asarray(max_steps),
            result=optx.RESULTS.successful,
            losses=losses,
        )
    params, result, steps = minimise(loss, solver, params, solver_args, max_steps)
    return FitResult(
        proposal=eqx.combine(params, static),
        loss=loss(params, solver_args),
        steps=steps,
        result=result,
    )


def fit_on_samples(
    proposal: Any,
    x: jax.Array,
    fx: jax.Array,
    log_q: jax.Array,
    *,
    weights: jax.Array | None = None,
    solver: optx.AbstractMinimiser | None = None,
    objective: str = "variance",
    max_steps: int = 256,
    filter_spec: Any = None,
) -> FitResult:
    r"""Fit `proposal` on samples already drawn from a frozen density $q$.

    Reuses one (expensive) batch for every step: the objective reweights the
    samples, e.g. for the variance $\log \frac1n\sum_i f(x_i)^2/(p_\theta(x_i) q(x_i))$
    (weights $f^2/(p\,q)$).

    **Arguments:**

    - `proposal`: the proposal to fit (its current parameters are the start).
    - `x`: the samples, `(n, d)` (or `(n,)`).
    - `fx`: `f(x)`, `(n, ...)`.
    - `log_q`: $\log q(x)$ of the density the samples came from, `(n,)`.
    - `weights`: per-sample weights summing to one (default $1/n$).
    - `solver`, `objective`, `max_steps`, `filter_spec`: as for `fit`.

    **Returns:** a `FitResult`.
    """
    proposal = check_proposal(proposal, methods=("sample", "log_pdf"))
    objective = check_choice(objective, "objective", OBJECTIVES)
    max_steps = check_count(max_steps, "max_steps")
    x = jnp.asarray(x)
    fx = jnp.asarray(fx)
    log_q = jnp.asarray(log_q)
    n = x.shape[0] if x.ndim else 0
    if n < 1 or fx.shape[:1] != (n,) or log_q.shape != (n,):
        raise ValueError(
            f"`x`, `fx` and `log_q` must share a leading axis n >= 1 (log_q of shape (n,)), "
            f"got {x.shape}, {fx.shape}, {log_q.shape}."
        )
    w = jnp.full((n,), 1.0 / n, log_q.dtype) if weights is None else jnp.asarray(weights)
    if w.shape != (n,):
        raise ValueError(f"`weights` must have shape ({n},), got {w.shape}.")
    params, static = split_parameters(proposal, filter_spec)
    solver = check_solver(solver, proposal, params)
    args = (x, log_abs(fx), log_q, w)

    def loss(p, args):
        xs, logf, lq, ws = args
        return objective_loss(objective, logf, eqx.combine(p, static).log_pdf(xs), ws, lq)

    params, result, steps = minimise(loss, solver, params, args, max_steps)
    return FitResult(eqx.combine(params, static), loss(params, args), steps, result)
