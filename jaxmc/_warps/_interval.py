"""Warps acting coordinate by coordinate: the uniform box, the power and exponential laws."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from .._box import clip_to_open_box
from ._common import _check_concrete, _float


# ---------------------------------------------------------------------------
# box


def box(u: ArrayLike, lo: ArrayLike, hi: ArrayLike) -> jax.Array:
    r"""Uniform point in the box $[lo, hi]$: $x = lo + u\,(hi - lo)$.

    The density is constant, $p(x) = 1/V$ with $V = \prod_j (hi_j - lo_j)$, so
    the CDF of each coordinate is $(x_j - lo_j)/(hi_j - lo_j)$ and its inverse
    is the affine map above (PBRT 3rd ed. §13.3.1). Points lie in the open box: one the
    map rounds onto a face (or `u` = 0) is moved to the nearest float inside, so
    an integrand singular on a face stays finite.

    **Arguments:**

    - `u`: shape `(..., k)`, points of $(0,1)^k$.
    - `lo`, `hi`: scalars or shape `(k,)` (or broadcastable to `u`), `lo < hi`.

    **Returns:** points of shape `(..., k)`.
    """
    u = _float(u)
    if u.ndim == 0:
        raise ValueError("`u` must have shape (..., k), got a scalar. Use shape (1,) for 1-D.")
    lo, hi = _float(lo), _float(hi)
    _check_concrete(lambda a, b: a < b, "`lo` must be < `hi`, got lo={}, hi={}.", lo, hi)
    u, lo, hi = jnp.broadcast_arrays(u, lo, hi)
    return clip_to_open_box(lo + u * (hi - lo), lo, hi)


def box_pdf(x: ArrayLike, lo: ArrayLike, hi: ArrayLike) -> jax.Array:
    """Density of `box`: $1/\\prod_j (hi_j - lo_j)$ inside the box, 0 outside; shape `x.shape[:-1]`."""
    x = _float(x)
    if x.ndim == 0:
        raise ValueError("`x` must have shape (..., k), got a scalar.")
    x, lo, hi = jnp.broadcast_arrays(x, _float(lo), _float(hi))
    inside = jnp.all((x >= lo) & (x <= hi), axis=-1)
    return jnp.where(inside, 1.0 / jnp.prod(hi - lo, axis=-1), 0.0)


def box_inverse(x: ArrayLike, lo: ArrayLike, hi: ArrayLike) -> jax.Array:
    """Inverse of `box`: $u = (x - lo)/(hi - lo)$."""
    x, lo, hi = jnp.broadcast_arrays(_float(x), _float(lo), _float(hi))
    return (x - lo) / (hi - lo)


# ---------------------------------------------------------------------------
# power (PBRT 3rd ed. §13.3.1)


def power(u: ArrayLike, n: ArrayLike) -> jax.Array:
    r"""Sample $p(x) = (n+1)\,x^n$ on $[0, 1]$ (PBRT 3rd ed. §13.3.1).

    Normalising $p(x) = c\,x^n$ gives $c = n + 1$; the CDF is
    $P(x) = x^{n+1}$, so inversion gives $X = U^{1/(n+1)}$. Used for Blinn-type
    lobes $\cos^n$. Differentiable in `n` (for $u > 0$) and `u`.

    **Arguments:**

    - `u`: uniform variate(s) in $(0, 1)$, any shape (the warp is 1-D).
    - `n`: the exponent, $n > -1$; broadcasts with `u`.

    **Returns:** `x` with the broadcast shape of `u` and `n`, in the open interval
    $(0, 1)$: a value that underflows to 0 (large $1/(n+1)$) or rounds to 1 is
    moved to the nearest float inside.
    """
    u, n = _float(u), _float(n)
    _check_concrete(lambda m: m > -1, "`n` must be > -1 (so that x^n is integrable), got {}.", n)
    positive = u > 0
    safe_u = jnp.where(positive, u, 1.0)
    # exp(log(u)/(n+1)) rather than u ** (1/(n+1)): same value, and the gradient
    # in `n` stays finite (0) at u = 0 instead of 0 * inf.
    x = jnp.where(positive, jnp.exp(jnp.log(safe_u) / (n + 1.0)), 0.0)
    return clip_to_open_box(x, 0.0, 1.0)


def power_pdf(x: ArrayLike, n: ArrayLike) -> jax.Array:
    """Density $(n+1)\\,x^n$ on $[0, 1]$, 0 outside."""
    x, n = _float(x), _float(n)
    inside = (x >= 0) & (x <= 1)
    safe_x = jnp.where(inside, x, 0.5)
    return jnp.where(inside, (n + 1.0) * safe_x**n, 0.0)


def power_inverse(x: ArrayLike, n: ArrayLike) -> jax.Array:
    """Inverse of `power`: the CDF $u = x^{n+1}$."""
    x, n = _float(x), _float(n)
    return x ** (n + 1.0)


# ---------------------------------------------------------------------------
# exponential (PBRT 3rd ed. §13.3.1)


def exponential(u: ArrayLike, a: ArrayLike) -> jax.Array:
    r"""Sample $p(x) = a\,e^{-a x}$ on $[0, \infty)$ (PBRT 3rd ed. §13.3.1).

    Normalising $c\,e^{-ax}$ gives $c = a$; the CDF is $P(x) = 1 - e^{-ax}$ and
    solving $U = 1 - e^{-aX}$ gives $X = -\ln(1 - U)/a$. A common shortcut
    replaces $1 - U$ by $U'$ (also uniform), i.e. $X = -\ln U'/a$. We keep $1 - U$: it is finite at
    $u = 0$ (for $u \in [0, 1)$) and keeps the map increasing, so stratified
    inputs stay ordered and `exponential_inverse` is the CDF itself.

    **Arguments:**

    - `u`: uniform variate(s) in $(0, 1)$, any shape.
    - `a`: the rate, $a > 0$; broadcasts with `u`.

    **Returns:** `x > 0` (a value that rounds to 0 is moved to the smallest
    positive normal float).
    """
    u, a = _float(u), _float(a)
    _check_concrete(lambda r: r > 0, "`a` must be > 0, got {}.", a)
    return clip_to_open_box(-jnp.log1p(-u) / a, 0.0, jnp.inf)


def exponential_pdf(x: ArrayLike, a: ArrayLike) -> jax.Array:
    """Density $a\\,e^{-a x}$ for $x \\ge 0$, 0 for $x < 0$."""
    x, a = _float(x), _float(a)
    return jnp.where(x >= 0, a * jnp.exp(-a * jnp.maximum(x, 0.0)), 0.0)


def exponential_inverse(x: ArrayLike, a: ArrayLike) -> jax.Array:
    """Inverse of `exponential`: the CDF $u = 1 - e^{-a x}$."""
    x, a = _float(x), _float(a)
    return -jnp.expm1(-a * x)
