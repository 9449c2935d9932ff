r"""The VEGAS-style adaptive loop: sample, estimate, refit, combine — traced end to end."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx

from .. import _random
from .._checks import check_callable, check_choice, check_count, check_key, evaluate, ratio
from ..proposals import Grid
from ..stats import Combined, Estimate, combine, estimate_iid
from ._fit import OBJECTIVES, _check_proposal, _check_solver, _log_abs, _objective, _split


def _check_fraction(value, name: str, lo: float = 0.0, hi: float = math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not lo <= value <= hi:
        raise ValueError(f"`{name}` must be a number in [{lo}, {hi}], got {value!r}.")
    return float(value)


def _sq_norm(y: jax.Array) -> jax.Array:
    return jnp.sum(jnp.reshape(y, (y.shape[0], -1)) ** 2, axis=-1)


def _strata(d: int, n: int, max_strata: int) -> int:
    """Strata per axis for VEGAS+: about four samples per hypercube at most."""
    ns = max(1, int((n / 4) ** (1.0 / d) + 1e-9))
    while ns > 1 and ns**d > max_strata:
        ns -= 1
    return ns


def _allocate(sigma: jax.Array, n: int, beta: float) -> jax.Array:
    r"""Samples per hypercube $n_h \propto \sigma_h^\beta$, at least 2 each, summing to `n`."""
    h = sigma.shape[0]
    s = jnp.where(jnp.isfinite(sigma) & (sigma > 0), sigma, 0.0) ** beta
    total = jnp.sum(s)
    share = jnp.where(total > 0, s / jnp.where(total > 0, total, 1.0), 1.0 / h)
    spare = n - 2 * h
    want = share * spare
    base = jnp.floor(want).astype(jnp.int32)
    rest = spare - jnp.sum(base)
    rank = jnp.argsort(jnp.argsort(-(want - base)))
    return 2 + base + (rank < rest).astype(jnp.int32)


def _stratified_step(grid: Grid, key, f, n: int, ns: int, sigma, beta, batched):
    """One VEGAS+ iteration on `grid`: returns (Estimate, x, per-sample refine weights, sigma)."""
    d = grid.dim
    h = ns**d
    counts = _allocate(sigma, n, beta)
    ends = jnp.cumsum(counts)
    cube = jnp.searchsorted(ends, jnp.arange(n), side="right")
    corner = jnp.stack(jnp.unravel_index(cube, (ns,) * d), axis=-1).astype(grid.lo.dtype)
    u = (corner + _random.uniform(key, (n, d), grid.lo.dtype)) / ns
    x, log_p = grid.map(u)
    xs = x[:, 0] if grid.event_ndim == 0 else x
    fx = evaluate(f, xs, batched)
    y, bad = ratio(fx, jnp.exp(log_p))
    cnt = counts.astype(y.dtype)
    shape = (h,) + (1,) * (y.ndim - 1)
    mean_h = jax.ops.segment_sum(y, cube, h) / jnp.reshape(cnt, shape)
    dev2 = (y - mean_h[cube]) ** 2
    var_h = jax.ops.segment_sum(dev2, cube, h) / jnp.reshape(cnt - 1, shape)
    vol = 1.0 / h
    mean = vol * jnp.sum(mean_h, axis=0)
    variance = vol**2 * jnp.sum(var_h / jnp.reshape(cnt, shape), axis=0)
    est = Estimate(
        mean=mean,
        variance=variance,
        n=jnp.asarray(n, jnp.int32),
        n_nonfinite=jnp.sum(bad, dtype=jnp.int32),
    )
    new_sigma = jnp.sqrt(jnp.sum(jnp.reshape(var_h, (h, -1)), axis=-1))
    refine_w = (vol / cnt[cube]) * _sq_norm(y)
    return est, xs, refine_w, new_sigma


def adapt(
    key: jax.Array,
    f: Callable,
    proposal: Any,
    *,
    iterations: int,
    n_per_iteration: int,
    warmup: int = 0,
    alpha: float = 0.5,
    stratify: bool = False,
    beta: float = 0.75,
    max_strata: int = 4096,
    solver: optx.AbstractMinimiser | None = None,
    fit_steps: int = 32,
    objective: str = "variance",
    batched: bool = False,
) -> tuple[Combined, Any]:
    r"""Adaptive importance sampling in the style of vegas: sample, estimate, refit, combine.

    Each of `iterations` rounds draws `n_per_iteration` points from the current
    proposal, estimates the integral from them (the importance estimator,
    eq. 10/12), and refits the proposal on the same evaluations:

    - a `Grid` by the VEGAS rule (`Grid.refine` with damping `alpha`, on the
      weights $(f/p)^2$); with `stratify=True` the unit cube of the grid's map is
      also cut into `ns**d` hypercubes and the samples are spread over them
      $\propto \sigma_h^\beta$ (adaptive stratified sampling of VEGAS+, Lepage
      2021), $\sigma_h$ the previous round's standard deviation of $f/p$ in
      hypercube $h$, at least two each;
    - any other proposal by `fit_steps` steps of `solver` (default BFGS) on the
      round's samples, reweighted from the frozen density they came from
      (`fit_on_samples`): no extra integrand evaluations.

    The rounds are then combined by `combine` (inverse-variance weights), so the
    result carries `chi2_dof` and `q` — a tiny `q` says the rounds disagree, e.g.
    because the early ones missed a peak — and the per-round estimates in
    `parts`. The first `warmup` rounds (whose density was still poor) are left
    out of the combination (and of `parts`); they still train the proposal.

    The loop is a `lax.scan` with static sizes, so `adapt` works under `jax.jit`
    and `jax.vmap` (e.g. over a parameter `f` closes over: a family of
    integrals in one compiled call). Pass the returned proposal back in to reuse
    it for a related integrand.

    **Arguments:**

    - `key`: a PRNG key (round `i` uses `fold_in(key, i)`).
    - `f`: the integrand, written for one point (or a batch with `batched=True`).
    - `proposal`: the starting proposal (`Grid`, `GaussianMixture`, `Flow`, ...).
    - `iterations`: number of rounds (static int >= 1).
    - `n_per_iteration`: integrand evaluations per round (static int).
    - `warmup`: rounds left out of the combination (`0 <= warmup < iterations`).
    - `alpha`: VEGAS damping exponent for `Grid` (vegas's default 0.5).
    - `stratify`, `beta`, `max_strata`: VEGAS+ stratification for `Grid`
      (`beta = 0` gives uniform allocation; at most `max_strata` hypercubes).
    - `solver`, `fit_steps`, `objective`: refitting of non-`Grid` proposals.
    - `batched`: `f` takes a batch.

    **Returns:** `(combined, proposal)` — a `Combined` and the adapted proposal.

    !!! Example

        ```python
        f = lambda x: jnp.exp(-100 * jnp.sum((x - 0.5) ** 2))
        grid = jaxmc.proposals.Grid(jnp.zeros(4), jnp.ones(4), bins=64)
        est, grid = jaxmc.fit.adapt(jax.random.key(0), f, grid, iterations=10,
                                    n_per_iteration=10_000, warmup=3)
        est.mean, est.stderr, est.chi2_dof, est.q
        ```
    """
    key = check_key(key)
    f = check_callable(f)
    proposal = _check_proposal(proposal)
    iterations = check_count(iterations, "iterations")
    n = check_count(n_per_iteration, "n_per_iteration", minimum=2)
    warmup = check_count(warmup, "warmup", minimum=0)
    if warmup >= iterations:
        raise ValueError(f"`warmup` must be < `iterations` = {iterations}, got {warmup}.")
    alpha = _check_fraction(alpha, "alpha")
    beta = _check_fraction(beta, "beta")
    max_strata = check_count(max_strata, "max_strata")
    fit_steps = check_count(fit_steps, "fit_steps")
    objective = check_choice(objective, "objective", OBJECTIVES)
    is_grid = isinstance(proposal, Grid)
    if stratify and not is_grid:
        raise ValueError(
            f"`stratify=True` needs a Grid proposal (VEGAS+), got {type(proposal).__name__}."
        )

    if is_grid:
        params, static = eqx.partition(proposal, eqx.is_array)
    else:
        params, static = _split(proposal, None)
        solver = _check_solver(solver, params)

    if stratify:
        ns = _strata(proposal.dim, n, max_strata)
        if 2 * ns**proposal.dim > n:
            raise ValueError(
                f"`n_per_iteration` = {n} is too small to stratify in {proposal.dim} dimensions."
            )
        sigma0 = jnp.ones((ns**proposal.dim,), proposal.lo.dtype)
    else:
        sigma0 = jnp.zeros((1,), jnp.result_type(float))

    def refit(prop, x, fx, log_q):
        def loss(p, args):
            xs, logf, lq = args
            w = jnp.full(lq.shape, 1.0 / lq.shape[0], lq.dtype)
            return _objective(objective, logf, eqx.combine(p, static).log_pdf(xs), w, lq)

        p0, _ = _split(prop, None)
        args = (x, _log_abs(fx), log_q)
        sol = optx.minimise(loss, solver, p0, args, max_steps=fit_steps, throw=False)
        # Keep the old parameters if the step went non-finite.
        new_loss = loss(sol.value, args)
        ok = jnp.isfinite(new_loss)
        p1 = jax.tree.map(lambda a, b: jnp.where(ok, a, b), sol.value, p0)
        return eqx.combine(p1, static)

    def body(carry, i):
        p, sigma = carry
        prop = eqx.combine(p, static)
        k = jax.random.fold_in(key, i)
        if stratify:
            est, x, w, sigma = _stratified_step(prop, k, f, n, ns, sigma, beta, batched)
            prop = prop.refine(x, w, alpha=alpha)
        else:
            x, px = prop.sample(k, n)
            fx = evaluate(f, x, batched)
            y, bad = ratio(fx, px)
            est = estimate_iid(y, bad)
            if is_grid:
                prop = prop.refine(x, _sq_norm(y) / n, alpha=alpha)
            else:
                prop = refit(prop, x, fx, jnp.log(px))
        p, _ = eqx.partition(prop, eqx.is_array) if is_grid else _split(prop, None)
        return (p, sigma), est

    (params, _), parts = jax.lax.scan(body, (params, sigma0), jnp.arange(iterations))
    parts = jax.tree.map(lambda a: a[warmup:], parts)
    return combine(parts), eqx.combine(params, static)
