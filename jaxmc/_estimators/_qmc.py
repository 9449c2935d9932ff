r"""Randomised quasi-Monte Carlo: independent randomisations of a low-discrepancy set."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from .._box import to_box
from .._checks import MAX_COUNT, check_bounds, check_callable, check_count, check_key
from .._diagnostics import bounded_variance
from .._integrand import bind, evaluate, ratio
from .._points._registry import unit_points
from .._stats import Estimate, diagnosed, tail_of


POINT_SETS = ("sobol", "halton", "lattice", "latin_hypercube", "stratified")


class QMCEstimate(Estimate):
    r"""A randomised-QMC `Estimate` that remembers its number of `replicas`.

    `variance` is $s^2/R$ from the spread of the $R$ replica means, with `dof`
    $R - 1$: `interval` is Student's t interval, as `scipy.integrate.qmc_quad`
    reports (with few replicas the normal one would be too narrow).
    """

    replicas: int = eqx.field(static=True)

    def t_interval(self, level: float = 0.95) -> tuple[jax.Array, jax.Array]:
        r"""$\mathrm{mean} \pm t_{R-1,(1+\ell)/2}\,\mathrm{stderr}$ (infinite for one
        replica): the same as `interval`, whose degrees of freedom are `dof` = $R - 1$."""
        return self.interval(level)


def _grid_counts(n: int, d: int) -> tuple[int, ...]:
    m = round(n ** (1.0 / d))
    for c in (m - 1, m, m + 1):
        if c >= 1 and c**d == n:
            return (c,) * d
    lower = max(int(math.floor(n ** (1.0 / d))), 1)
    raise ValueError(
        f'`n` must be a perfect d-th power for points="stratified" (one point per cell of a '
        f"cubic grid), got n={n} with d={d}; e.g. n={lower**d} or n={(lower + 1) ** d}. "
        "For other grids pass a callable `points`."
    )


def _point_generator(points: Any, n: int, d: int) -> Callable[[jax.Array], jax.Array]:
    """A function key -> `(n, d)` points for the named (or callable) point set."""
    if callable(points):
        return lambda k: points(k, n, d)
    if not isinstance(points, str) or points not in POINT_SETS:
        raise ValueError(
            f"`points` must be one of {POINT_SETS} or a callable (key, n, d) -> (n, d), "
            f"got {points!r}."
        )
    counts = _grid_counts(n, d) if points == "stratified" else None
    return lambda k: unit_points(points, k, n, d, counts=counts)


def randomized_qmc(
    key: jax.Array,
    f: Callable,
    lo: Any,
    hi: Any,
    n: int,
    *,
    points: str | Callable = "sobol",
    replicas: int = 16,
    batched: bool = False,
    args: Any = None,
) -> QMCEstimate:
    r"""Randomised quasi-Monte Carlo: the mean over independent randomisations of a point set.

    Each of the $R$ = `replicas` randomisations $u^{(r)}_1..u^{(r)}_n$ of an
    $n$-point set (scrambled Sobol' by default) gives the equal-weight rule
    $\hat I_r = \frac{V}{n}\sum_i f(lo + (hi - lo) u^{(r)}_i)$, unbiased because
    every randomised point is marginally uniform. The $\hat I_r$ are i.i.d., so

    $$\hat I = \frac1R \sum_r \hat I_r, \qquad \widehat V[\hat I] = \frac{s^2}{R},\quad
    s^2 = \frac{1}{R-1}\sum_r (\hat I_r - \hat I)^2,$$

    as in `scipy.integrate.qmc_quad` (Owen, *Practical Quasi-Monte Carlo
    Integration*, ch. 17). For smooth $f$ the error of scrambled Sobol' decays
    like $n^{-1}$ (up to logs) or faster, against plain MC's $n^{-1/2}$; keep $n$
    a power of 2 for Sobol' (its balance properties hold for $2^m$ points).

    **Arguments:**

    - `key`: a PRNG key.
    - `f`: the integrand, written for one point.
    - `lo`, `hi`: the box.
    - `n`: points per replica (static int).
    - `points`: `"sobol"` (default), `"halton"`, `"lattice"` (randomly shifted
      rank-1 lattice), `"latin_hypercube"`, `"stratified"` (jittered cubic grid;
      `n` must be a $d$-th power), or a callable `(key, n, d) -> (n, d)` of
      points on $[0,1)^d$, each marginally uniform.
    - `replicas`: $R$, independent randomisations (static int; with 1 the
      variance is `inf`). A few (8–32) suffice; more spend points on error bars.
    - `batched`: if True, `f` receives all $nR$ points at once.
    - `args`: parameters of `f` (any pytree); if given, `f` is called as `f(x, args)`.

    **Returns:** a `QMCEstimate` (an `Estimate`) with `n = n·R` evaluations;
    `est.t_interval(0.95)` gives the Student-t interval with $R-1$ degrees of
    freedom.

    !!! Example

        ```python
        est = randomized_qmc(key, lambda x: jnp.prod(x), jnp.zeros(3), jnp.ones(3), 1024)
        low, high = est.t_interval(0.95)
        ```
    """
    key = check_key(key)
    f = bind(check_callable(f), args)
    lo, hi = check_bounds(lo, hi, finite_volume=True)
    n = check_count(n)
    replicas = check_count(replicas, "replicas")
    if n * replicas > MAX_COUNT:
        raise ValueError(
            f"`n` * `replicas` = {n * replicas:,} evaluations must be at most 2**31 - 1 "
            "(counts are int32)."
        )
    d = 1 if lo.ndim == 0 else lo.shape[0]
    generate = _point_generator(points, n, d)
    keys = jax.random.split(key, replicas)
    u = jax.vmap(generate)(keys)
    if u.shape != (replicas, n, d):
        raise ValueError(
            f"`points` must give an array of shape (n, d) = ({n}, {d}), got {u.shape[1:]}."
        )
    u = jnp.asarray(u, dtype=lo.dtype)
    if lo.ndim == 0:
        u = u[..., 0]
    x = to_box(u.reshape((replicas * n,) + lo.shape), lo, hi)
    fx = evaluate(f, x, batched)
    volume = jnp.prod(hi - lo)
    y, bad = ratio(fx, jnp.broadcast_to(1.0 / volume, (replicas * n,)))
    per_replica = jnp.mean(y.reshape((replicas, n) + y.shape[1:]), axis=1)
    mean = jnp.mean(per_replica, axis=0)
    if replicas > 1:
        variance = jnp.sum((per_replica - mean) ** 2, axis=0) / (replicas - 1) / replicas
    else:
        variance = jnp.full(mean.shape, jnp.inf, mean.dtype)
    tail = tail_of(y)
    variance, conservative = bounded_variance(variance, mean, tail)
    return QMCEstimate(
        **diagnosed(
            mean,
            variance,
            jnp.asarray(n * replicas, dtype=jnp.int32),
            jnp.sum(bad, dtype=jnp.int32),
            tail,
            conservative,
            dof=replicas - 1,
        ),
        replicas=replicas,
    )

