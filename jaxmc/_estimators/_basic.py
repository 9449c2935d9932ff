r"""The basic estimator over a box (eq. 8) and importance sampling (eq. 10/12)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from .. import _random
from .._box import to_box
from .._checks import MAX_COUNT, check_bounds, check_callable, check_count, check_key
from .._diagnostics import warn_if_unreliable
from .._integrand import bind, evaluate, ratio
from .._stats import Estimate, estimate_iid
from ..proposals import check_proposal


def uniform(
    key: jax.Array,
    f: Callable,
    lo: Any,
    hi: Any,
    n: int,
    *,
    batched: bool = False,
    args: Any = None,
) -> Estimate:
    r"""The basic Monte Carlo estimator over the box $[lo, hi]$ (eq. 8).

    $$F_n = \frac{V}{n}\sum_{i=1}^n f(X_i),\qquad X_i \sim \mathcal U[lo, hi],\quad
    V = \prod_j (hi_j - lo_j),$$

    unbiased (eq. 9), with variance $V[F_n] = V[V f(X)]/n$ (eq. 13) estimated
    from the sample variance.

    **Arguments:**

    - `key`: a PRNG key.
    - `f`: the integrand, written for one point (a scalar for scalar bounds, a
      `(d,)` array for `(d,)` bounds); returns a scalar or any fixed-shape array.
    - `lo`, `hi`: the box, scalars or shape `(d,)`, with `lo < hi`.
    - `n`: the number of samples (a static Python int).
    - `batched`: if True, `f` receives all points at once (`(n, d)` or `(n,)`)
      and returns `(n, ...)`.
    - `args`: parameters of `f` (any pytree); if given, `f` is called as
      `f(x, args)` (see `integrate`).

    **Returns:** an `Estimate`.

    !!! Example

        ```python
        est = jaxmc.uniform(jax.random.key(0), lambda x: x**2, 0.0, 1.0, 10_000)
        est.mean, est.stderr  # ≈ 1/3 ± 0.003
        ```
    """
    key = check_key(key)
    f = bind(check_callable(f), args)
    lo, hi = check_bounds(lo, hi, finite_volume=True)
    n = check_count(n, maximum=MAX_COUNT)
    u = _random.uniform(key, (n,) + lo.shape, lo.dtype)
    x = to_box(u, lo, hi)
    fx = evaluate(f, x, batched)
    volume = jnp.prod(hi - lo)
    y, bad = ratio(fx, jnp.broadcast_to(1.0 / volume, (n,)))
    est = estimate_iid(y, bad)
    warn_if_unreliable(est, "uniform")
    return est


def importance(
    key: jax.Array,
    f: Callable,
    proposal: Any,
    n: int,
    *,
    batched: bool = False,
    args: Any = None,
) -> Estimate:
    r"""Importance sampling (eq. 10/12): $F_n = \frac1n \sum_{i=1}^n f(X_i)/p(X_i)$, $X_i \sim p$.

    Unbiased wherever $p > 0$ on the support of $f$ (eq. 11), with variance
    $\frac1n V_p[f/p]$ (eq. 13) — zero when $p \propto |f|$ and $f$ has one
    sign (§4.1). Samples with $p(X_i) = 0$ and $f(X_i) \ne 0$, or non-finite
    $f$, contribute zero and are counted in `n_nonfinite`.

    **Arguments:**

    - `key`: a PRNG key.
    - `f`: the integrand, written for one point (see `uniform`).
    - `proposal`: any object with `sample(key, n) -> (x, pdf)` and `pdf(x)`,
      e.g. `jaxmc.proposals.Uniform(lo, hi)`.
    - `n`: the number of samples (a static Python int).
    - `batched`: if True, `f` receives the whole batch `x`.
    - `args`: parameters of `f` (any pytree); if given, `f` is called as `f(x, args)`.

    **Returns:** an `Estimate`.

    Gradients with respect to the proposal's parameters are the
    reparameterised ones: the key fixes the base randomness and `x` moves with
    the parameters.
    """
    key = check_key(key)
    f = bind(check_callable(f), args)
    proposal = check_proposal(proposal)
    n = check_count(n, maximum=MAX_COUNT)
    x, px = proposal.sample(key, n)
    fx = evaluate(f, x, batched)
    y, bad = ratio(fx, jnp.asarray(px))
    est = estimate_iid(y, bad)
    warn_if_unreliable(est, "importance")
    return est
