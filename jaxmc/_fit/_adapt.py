r"""The VEGAS-style adaptive loop: sample, estimate, refit, combine — traced end to end."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .. import _random
from .._checks import check_callable, check_choice, check_count, check_key, evaluate, ratio
from ..proposals import Grid, Partition
from ..stats import Combined, Estimate, combine, estimate_iid
from ._fit import OBJECTIVES, _check_proposal, _check_solver, _log_abs, _objective, _split
from ._partition import _stratified_round


def _check_fraction(value, name: str, lo: float = 0.0, hi: float = math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not lo <= value <= hi:
        raise ValueError(f"`{name}` must be a number in [{lo}, {hi}], got {value!r}.")
    return float(value)


def _sq_norm(y: jax.Array) -> jax.Array:
    return jnp.sum(jnp.reshape(y, (y.shape[0], -1)) ** 2, axis=-1)


# Share of each round's samples spread evenly over the hypercubes (at least two per
# cube); the rest go where sigma_h is large. vegas's default `neval_frac` is the
# adaptive share, 0.75.
_UNIFORM_SHARE = 0.25
# Hypercube indices are turned into corners in float arithmetic (`_corners`): exact below this.
_MAX_STRATA = 2**22


def _strata(d: int, n: int, max_strata: int) -> tuple[int, ...]:
    r"""Strata per axis for VEGAS+, as vegas chooses them.

    $n_s = \lfloor (n_0/2)^{1/d} \rfloor$ with $n_0$ the evenly spread share of
    the `n` samples, so each hypercube gets about two of those; then as many axes
    as still fit get $n_s + 1$ strata. At most `max_strata` hypercubes.
    """
    n0 = _UNIFORM_SHARE * n
    ns = max(1, int((n0 / 2) ** (1.0 / d) + 1e-9))
    while ns > 1 and ns**d > max_strata:
        ns -= 1
    strata = [ns] * d
    for j in range(d):
        bigger = strata.copy()
        bigger[j] += 1
        if 2 * math.prod(bigger) > n0 or math.prod(bigger) > max_strata:
            break
        strata = bigger
    return tuple(strata)


def _allocate(sigma: jax.Array, n: int, beta) -> jax.Array:
    r"""Samples per hypercube: an even floor $m_0 \ge 2$ each plus the rest $\propto \sigma_h^\beta$.

    The proportional shares are rounded systematically (the rounded cumulative
    sum is differenced), so the counts sum to `n` exactly and each is within one
    of its share: no sort, which matters at thousands of hypercubes.
    """
    h = sigma.shape[0]
    m0 = max(2, int(_UNIFORM_SHARE * n / h))
    spare = n - m0 * h
    s = jnp.where(jnp.isfinite(sigma) & (sigma > 0), sigma, 0.0) ** beta
    total = jnp.sum(s)
    share = jnp.where(total > 0, s / jnp.where(total > 0, total, 1.0), 1.0 / h)
    cum = jnp.minimum(jnp.floor(jnp.cumsum(share) * spare + 0.5), spare).astype(jnp.int32)
    # A float cumsum summed as a tree (as XLA does on the CPU) can step down by a rounding
    # error; a running maximum restores monotone counts, so no cube drops below m0.
    cum = jax.lax.cummax(cum).at[-1].set(spare)
    return m0 + jnp.diff(cum, prepend=0)


def _hypercube_of_sample(counts: jax.Array, n: int) -> jax.Array:
    """Hypercube index of each of the `n` samples, laid out cube by cube (`counts` per cube)."""
    starts = jnp.cumsum(counts)[:-1]
    return jnp.cumsum(jnp.zeros((n,), jnp.int32).at[starts].add(1))


def _corners(cube: jax.Array, strata: tuple[int, ...], dtype) -> jax.Array:
    """Lower corner (in strata units) of each hypercube, `(n,) -> (n, d)`, row-major order.

    Float arithmetic, exact for fewer than 2^22 hypercubes: `jnp.unravel_index`'s
    integer divisions run as a scalar loop on the CPU.
    """
    dtype = jnp.promote_types(dtype, jnp.float32)
    strides = np.array([math.prod(strata[j + 1 :]) for j in range(len(strata))], dtype)
    c = cube.astype(dtype)[:, None] + 0.5
    q = jnp.floor(c / strides)  # cube // stride, per axis
    sizes = np.asarray(strata, dtype)
    return q - sizes * jnp.floor((q + 0.5) / sizes)  # ... % strata


class _Draw(eqx.Module):
    """One VEGAS+ round's points on the unit cube, laid out hypercube by hypercube."""

    u: jax.Array  # (n, d) points
    cube: jax.Array  # (n,) hypercube of each point, non-decreasing
    counts: jax.Array  # (H,) points per hypercube


def _stratified_draw(raw, sigma, n: int, strata, beta) -> _Draw:
    """Spread `n` points over the hypercubes by `_allocate` and jitter them with `raw` uniforms."""
    counts = _allocate(sigma, n, beta)
    cube = _hypercube_of_sample(counts, n)
    corner = _corners(cube, strata, raw.dtype)
    u = ((corner + raw) / np.asarray(strata, corner.dtype)).astype(raw.dtype)
    return _Draw(u, cube, counts)


def _stratified_step(grid: Grid, table, draw: _Draw, f, n: int, strata, alpha, batched):
    r"""One VEGAS+ round on `grid`: the estimate, the refined grid and the new $\sigma_h$.

    The unit cube of the grid's map is cut into `prod(strata)` hypercubes $h$
    of volume $v = 1/H$; cube $h$ gets $n_h$ samples (`_allocate`), and
    $\hat I = v \sum_h \bar y_h$, $\hat V = v^2 \sum_h s_h^2 / n_h$ with
    $y = f/p$ and $\bar y_h$, $s_h^2$ the cube's sample mean and variance
    (stratified sampling, §4.2).
    """
    h = math.prod(strata)
    u, cube, counts = draw.u, draw.cube, draw.counts
    x, log_p, bins = grid._map(u, table)
    xs = x[:, 0] if grid.event_ndim == 0 else x
    fx = evaluate(f, xs, batched)
    y, bad = ratio(fx, jnp.exp(log_p))
    cnt = counts.astype(y.dtype)
    shape = (h,) + (1,) * (y.ndim - 1)
    mean_h = jax.ops.segment_sum(y, cube, h, indices_are_sorted=True) / jnp.reshape(cnt, shape)
    dev2 = (y - mean_h[cube]) ** 2
    var_h = jax.ops.segment_sum(dev2, cube, h, indices_are_sorted=True) / jnp.reshape(
        cnt - 1, shape
    )
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
    # Each sample stands for volume v / n_h of the unit cube: the per-bin sums
    # estimate the integral of (f/p)^2 over each bin, whatever the allocation.
    refine_w = (vol / cnt[cube]) * _sq_norm(y)
    return est, grid._refine_bins(bins, refine_w, alpha=alpha), new_sigma


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
    max_strata: int = 2**16,
    passes: int = 4,
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
      also cut into hypercubes (about $n/8$ of them, as vegas does) and the
      samples are spread over them: a quarter evenly (at least two per cube),
      the rest $\propto \sigma_h^\beta$ (adaptive stratified sampling of VEGAS+,
      Lepage 2021), $\sigma_h$ the previous round's standard deviation of $f/p$
      in hypercube $h$;
    - a `Partition` is always sampled stratified: each leaf (cell) gets two
      points, a quarter of the rest evenly and the rest
      $\propto (V_c\sigma_c)^\beta$ ($V_c$ its volume, $\sigma_c$ the pooled
      standard deviation of $f$ in it; Neyman allocation at $\beta = 1$);
      then `passes` times on the round's points, the leaves with the largest
      $V_c\sigma_c$ (and coarse leaves next to them) are halved along their
      longest edge, as many as `max_cells` allows, and the cell masses are
      set to $\propto V_c \sqrt{\overline{f^2}}$ (MISER-like recursive
      stratified sampling, Press & Farrar 1990). Needs `n_per_iteration >=
      4 * max_cells`;
    - any other proposal by `fit_steps` steps of `solver` (default as for
      `fit`: BFGS, L-BFGS above 2000 parameters, Adam for a `Flow`) on the
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
      (`beta = 0` gives uniform allocation; at most `max_strata <= 2**22`
      hypercubes).
    - `passes`: rounds of cell splitting per iteration for `Partition`
      (static int >= 1; each can double the number of cells).
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
    if max_strata > _MAX_STRATA:
        raise ValueError(f"`max_strata` must be at most 2**22, got {max_strata}.")
    fit_steps = check_count(fit_steps, "fit_steps")
    objective = check_choice(objective, "objective", OBJECTIVES)
    passes = check_count(passes, "passes")
    is_grid = isinstance(proposal, Grid)
    is_partition = isinstance(proposal, Partition)
    if is_partition and n < 4 * proposal.max_cells:
        raise ValueError(
            "A Partition needs `n_per_iteration` >= 4 * max_cells (two points per cell "
            f"and as many to spare) = {4 * proposal.max_cells}, got {n}."
        )
    if stratify and not is_grid:
        raise ValueError(
            f"`stratify=True` needs a Grid proposal (VEGAS+), got {type(proposal).__name__}."
        )

    if is_grid or is_partition:
        params, static = eqx.partition(proposal, eqx.is_array)
    else:
        params, static = _split(proposal, None)
        solver = _check_solver(solver, proposal, params)

    if stratify:
        strata = _strata(proposal.dim, n, max_strata)  # at least two samples per cube
        sigma0 = jnp.ones((math.prod(strata),), proposal.lo.dtype)
    elif is_partition:
        # Each node's pooled (weight, variance, mean square); equal to start.
        sigma0 = jnp.ones(proposal.logits.shape + (3,), proposal.lo.dtype).at[:, 0].set(0.0)
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

    def uniforms(i):
        return _random.uniform(jax.random.fold_in(key, i), (n, proposal.dim), proposal.lo.dtype)

    def next_draw(i, sigma):
        raw = uniforms(i)
        return _stratified_draw(raw, sigma, n, strata, beta) if stratify else raw

    def body(carry, i):
        p, draw, table = carry
        prop = eqx.combine(p, static)
        if is_grid:
            if stratify:
                est, prop, sigma = _stratified_step(
                    prop, table, draw, f, n, strata, alpha, batched
                )
            else:
                x, log_p, bins = prop._map(draw, table)
                x = x[:, 0] if prop.event_ndim == 0 else x
                y, bad = ratio(evaluate(f, x, batched), jnp.exp(log_p))
                est = estimate_iid(y, bad)
                prop = prop._refine_bins(bins, _sq_norm(y) / n, alpha=alpha)
                sigma = None
            # Round i + 1's points (its allocation needs only this round's sigma) and
            # the refined grid's table are made now and carried. Loop-carried arrays
            # are stored, so neither the random generator, the allocation nor the
            # table's softmax is re-run inside the map's gathers, which XLA on the CPU
            # would otherwise fuse them into (a scalar loop).
            draw = next_draw(i + 1, sigma)
            table = prop._table()
            p, _ = eqx.partition(prop, eqx.is_array)
        elif is_partition:
            # `draw` carries the nodes' pooled statistics, which set the next allocation.
            est, prop, draw = _stratified_round(
                prop, draw, uniforms(i), f, n, beta, passes, batched
            )
            p, _ = eqx.partition(prop, eqx.is_array)
        else:
            x, px = prop.sample(jax.random.fold_in(key, i), n)
            fx = evaluate(f, x, batched)
            y, bad = ratio(fx, px)
            est = estimate_iid(y, bad)
            p, _ = _split(refit(prop, x, fx, jnp.log(px)), None)
        return (p, draw, table), est

    if is_grid:
        init = (params, next_draw(0, sigma0), proposal._table())
    elif is_partition:
        init = (params, sigma0, None)
    else:
        init = (params, jnp.zeros((), proposal.lo.dtype), None)
    (params, _, _), parts = jax.lax.scan(body, init, jnp.arange(iterations))
    parts = jax.tree.map(lambda a: a[warmup:], parts)
    return combine(parts), eqx.combine(params, static)
