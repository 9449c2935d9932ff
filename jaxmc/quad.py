r"""Deterministic quadrature baselines (eq. 1, 2 of the lecture).

Every rule here has the form of eq. 1, a weighted sum of integrand values at
fixed nodes,

$$\hat I = \sum_{i} w_i f(x_i),$$

and extends to a box $[lo, hi] \subset \mathbb R^d$ by the tensor product of
eq. 2: with $m$ nodes per axis, $\hat I = \sum_{i_1, \dots, i_d}
w_{i_1} \cdots w_{i_d}\, f(x_{i_1}, \dots, x_{i_d})$ over all $N = m^d$ grid
points.

| rule | nodes per axis | error (1-D, $h = (b-a)/n$) | exact for degree |
| --- | --- | --- | --- |
| `midpoint` | $n$ | $O(h^2)$ | 1 |
| `trapezoid` | $n+1$ | $O(h^2)$ | 1 |
| `simpson` | $n+1$ ($n$ even) | $O(h^4)$ | 3 |
| `gauss_legendre` | $n$ | $O(\rho^{-2n})$ for analytic $f$ | $2n-1$ |

**The curse of dimension.** A rule with error $O(n^{-r})$ in 1-D ($r = 2$ or
$4$) needs $N = n^d$ evaluations on the tensor grid, so in terms of
evaluations its error is $O(N^{-r/d})$: Simpson's rule in $d = 8$ converges
like $N^{-1/2}$, no better than Monte Carlo, whose error is $O(N^{-1/2})$ in
any dimension (§1.2; the lecture writes the exponents the other way round).
These functions are baselines for that comparison, not adaptive integrators.

All functions follow the estimators' conventions: `f` is written for one point
(a scalar for scalar bounds, a `(d,)` array for `(d,)` bounds) and may return
any fixed-shape array; bounds are traced (so `jit`, `vmap` and `grad` work with
respect to them and to anything `f` closes over); `n` is a static Python int.
Each rule runs as one compiled computation, cached per integrand object, `n`
and bounds shape, so integrating the same `f` again does not recompile.
The grid is evaluated in chunks of at most `chunk` points (a `lax.map` over
chunks), so memory stays bounded however large $N$ is; more than
`MAX_EVALUATIONS` ($2^{27}$) evaluations is refused with a `ValueError`.

!!! Example

    ```python
    import jax.numpy as jnp
    from jaxmc import quad

    quad.simpson(jnp.exp, 0.0, 1.0, 16)  # e - 1, with error 1.5e-7
    quad.gauss_legendre(lambda x: jnp.prod(jnp.cos(x)), jnp.zeros(3), jnp.ones(3), 8)
    # sin(1)**3 to float precision, from 8**3 = 512 evaluations
    ```
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._checks import check_bounds, check_callable, check_count
from ._integrand import evaluate


__all__ = ["MAX_EVALUATIONS", "gauss_legendre", "midpoint", "simpson", "trapezoid"]

#: The largest tensor grid (number of integrand evaluations) a rule will evaluate.
MAX_EVALUATIONS = 2**27

_DEFAULT_CHUNK = 2**16


# ---------------------------------------------------------------------------
# 1-D reference rules on [0, 1], in float64 numpy at trace time (sizes static).
# Weights sum to 1; the box's volume is applied afterwards.


def _frozen(*arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    for a in arrays:
        a.setflags(write=False)
    return arrays


@functools.lru_cache(maxsize=64)
def _midpoint_rule(n: int) -> tuple[np.ndarray, np.ndarray]:
    t = (np.arange(n, dtype=np.float64) + 0.5) / n
    w = np.full(n, 1.0 / n)
    return _frozen(t, w)


@functools.lru_cache(maxsize=64)
def _trapezoid_rule(n: int) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(n + 1, dtype=np.float64) / n
    w = np.full(n + 1, 1.0 / n)
    w[0] = w[-1] = 0.5 / n
    return _frozen(t, w)


@functools.lru_cache(maxsize=64)
def _simpson_rule(n: int) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(n + 1, dtype=np.float64) / n
    w = np.where(np.arange(n + 1) % 2 == 1, 4.0, 2.0)
    w[0] = w[-1] = 1.0
    return _frozen(t, w / (3.0 * n))


@functools.lru_cache(maxsize=64)
def _gauss_legendre_rule(n: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(n)
    return _frozen((x + 1.0) / 2.0, w / 2.0)


# ---------------------------------------------------------------------------
# Tensor-product evaluation.


def _tensor_rule(
    f: Callable,
    lo: Any,
    hi: Any,
    n: int,
    rule: Callable[[int], tuple[np.ndarray, np.ndarray]],
    *,
    batched: bool,
    chunk: int,
    even: bool = False,
) -> jax.Array:
    f = check_callable(f)
    n = check_count(n, "n")
    if even and n % 2:
        raise ValueError(f"`n` must be even for Simpson's rule (pairs of intervals), got {n}.")
    chunk = check_count(chunk, "chunk")
    if not isinstance(batched, bool):
        raise TypeError(f"`batched` must be a bool, got {type(batched).__name__}.")
    lo, hi = check_bounds(lo, hi)
    scalar = lo.ndim == 0
    d = 1 if scalar else lo.shape[0]

    t_np, w_np = rule(n)
    m = t_np.shape[0]
    total = m**d
    if total > MAX_EVALUATIONS:
        raise ValueError(
            f"`n`={n} in d={d} dimensions needs {m}^{d} = {total:,} integrand evaluations, "
            f"more than MAX_EVALUATIONS = {MAX_EVALUATIONS:,}. Tensor-product "
            "quadrature scales as n^d (the curse of dimension); lower `n`, or use a Monte "
            "Carlo estimator such as jaxmc.uniform in this dimension."
        )

    return _evaluate_rule(_ByIdentity(f), lo, hi, rule, n, batched, chunk)


class _ByIdentity:
    """Wrap `f` as a static `jit` argument compared by identity.

    Integrands may be unhashable (e.g. modules holding arrays); identity keeps
    the compilation cache valid for them and reuses it when the same `f` is
    integrated again.
    """

    __slots__ = ("f",)

    def __init__(self, f: Callable):
        self.f = f

    def __hash__(self) -> int:
        return id(self.f)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, _ByIdentity) and other.f is self.f


# One compilation per call instead of one per primitive in eager mode; sizes
# and the integrand are static, the bounds are traced.
@functools.partial(jax.jit, static_argnums=(0, 3, 4, 5, 6))
def _evaluate_rule(
    wrapped: _ByIdentity,
    lo: jax.Array,
    hi: jax.Array,
    rule: Callable[[int], tuple[np.ndarray, np.ndarray]],
    n: int,
    batched: bool,
    chunk: int,
) -> jax.Array:
    f = wrapped.f
    scalar = lo.ndim == 0
    d = 1 if scalar else lo.shape[0]
    t_np, w_np = rule(n)
    m = t_np.shape[0]
    total = m**d
    dtype = lo.dtype
    nodes = jnp.asarray(t_np, dtype=dtype)
    weights = jnp.asarray(w_np, dtype=dtype)
    lo_v = jnp.reshape(lo, (d,))
    width = jnp.reshape(hi - lo, (d,))
    # Flat index k ↔ digits (i_1, ..., i_d) in base m, the first axis slowest.
    strides = jnp.asarray(m ** np.arange(d - 1, -1, -1), dtype=jnp.int32)
    size = min(chunk, total)
    n_chunks = -(-total // size)

    def block(start: jax.Array) -> jax.Array:
        k = start + jnp.arange(size, dtype=jnp.int32)
        valid = k < total
        # Padding in the last chunk reuses grid point 0 with weight 0, so f is
        # only ever evaluated at grid points.
        k = jnp.where(valid, k, 0)
        digits = (k[:, None] // strides[None, :]) % m  # (size, d)
        x = lo_v[None, :] + width[None, :] * nodes[digits]
        w = jnp.where(valid, jnp.prod(weights[digits], axis=1), 0)
        fx = evaluate(f, x[:, 0] if scalar else x, batched)
        out = jnp.promote_types(fx.dtype, dtype)
        return jnp.tensordot(w.astype(out), fx.astype(out), axes=1)

    if n_chunks == 1:
        acc = block(jnp.zeros((), jnp.int32))
    else:
        starts = jnp.arange(n_chunks, dtype=jnp.int32) * size
        # One partial sum per chunk, summed at the end: float32 stays accurate
        # because no long running sum is carried through the loop.
        acc = jnp.sum(jax.lax.map(block, starts), axis=0)
    volume = jnp.prod(width)
    return volume.astype(acc.dtype) * acc


def midpoint(
    f: Callable,
    lo: Any,
    hi: Any,
    n: int,
    *,
    batched: bool = False,
    chunk: int = _DEFAULT_CHUNK,
) -> jax.Array:
    r"""Composite midpoint (rectangle) rule, eq. 1 with $x_i$ the centres of $n$ cells.

    $$\hat I_R = h \sum_{i=0}^{n-1} f\big(a + (i + \tfrac12) h\big),\qquad h = \frac{b-a}{n},$$

    with error $|\hat I_R - I| \le \frac{(b-a)}{24} h^2 \max|f''| = O(n^{-2})$.
    Exact for polynomials of degree 1. With `(d,)` bounds, the tensor product
    (eq. 2) over $n^d$ cell centres, error $O(n^{-2}) = O(N^{-2/d})$ for $N$
    evaluations.

    **Arguments:**

    - `f`: the integrand, written for one point (a scalar for scalar bounds, a
      `(d,)` array for `(d,)` bounds); returns a scalar or any fixed-shape array.
    - `lo`, `hi`: the box, scalars or shape `(d,)`, with `lo < hi` (may be traced).
    - `n`: the number of cells per axis (a static Python int).
    - `batched`: if True, `f` receives a batch of points (`(k, d)` or `(k,)`,
      `k <= chunk`) and returns `(k, ...)`.
    - `chunk`: the largest number of points evaluated at once.

    **Returns:** $\hat I$, an array with the shape of `f`'s output.

    **Raises:** `ValueError` if `n < 1`, the bounds are malformed or
    `lo >= hi`, or the grid has more than `MAX_EVALUATIONS` points; `TypeError`
    if `n` is not an int or `f` is not callable.
    """
    return _tensor_rule(f, lo, hi, n, _midpoint_rule, batched=batched, chunk=chunk)


def trapezoid(
    f: Callable,
    lo: Any,
    hi: Any,
    n: int,
    *,
    batched: bool = False,
    chunk: int = _DEFAULT_CHUNK,
) -> jax.Array:
    r"""Composite trapezoidal rule on $n$ intervals ($n + 1$ nodes per axis).

    $$\hat I_T = h\Big[\tfrac12 f(x_0) + f(x_1) + \dots + f(x_{n-1}) + \tfrac12 f(x_n)\Big],
    \qquad x_i = a + i h,\ h = \frac{b-a}{n},$$

    with error $|\hat I_T - I| \le \frac{(b-a)}{12} h^2 \max|f''| = O(n^{-2})$.
    Exact for polynomials of degree 1. With `(d,)` bounds, the tensor product
    (eq. 2) over $(n+1)^d$ grid points, error $O(N^{-2/d})$ for $N$ evaluations.

    **Arguments:**

    - `f`: the integrand, written for one point (a scalar for scalar bounds, a
      `(d,)` array for `(d,)` bounds); returns a scalar or any fixed-shape array.
    - `lo`, `hi`: the box, scalars or shape `(d,)`, with `lo < hi` (may be traced).
    - `n`: the number of intervals per axis (a static Python int).
    - `batched`: if True, `f` receives a batch of points (`(k, d)` or `(k,)`,
      `k <= chunk`) and returns `(k, ...)`.
    - `chunk`: the largest number of points evaluated at once.

    **Returns:** $\hat I$, an array with the shape of `f`'s output.

    **Raises:** `ValueError` if `n < 1`, the bounds are malformed or
    `lo >= hi`, or the grid has more than `MAX_EVALUATIONS` points; `TypeError`
    if `n` is not an int or `f` is not callable.
    """
    return _tensor_rule(f, lo, hi, n, _trapezoid_rule, batched=batched, chunk=chunk)


def simpson(
    f: Callable,
    lo: Any,
    hi: Any,
    n: int,
    *,
    batched: bool = False,
    chunk: int = _DEFAULT_CHUNK,
) -> jax.Array:
    r"""Composite Simpson rule on $n$ intervals ($n$ even, $n + 1$ nodes per axis).

    A parabola through each pair of intervals:

    $$\hat I_S = \frac h3\Big[f(x_0) + 4 f(x_1) + 2 f(x_2) + 4 f(x_3) + \dots
    + 4 f(x_{n-1}) + f(x_n)\Big],\qquad h = \frac{b-a}{n},$$

    with error $|\hat I_S - I| \le \frac{(b-a)}{180} h^4 \max|f^{(4)}| = O(n^{-4})$.
    Exact for polynomials of degree 3. With `(d,)` bounds, the tensor product
    (eq. 2) over $(n+1)^d$ grid points, error $O(N^{-4/d})$ for $N$ evaluations.

    **Arguments:**

    - `f`: the integrand, written for one point (a scalar for scalar bounds, a
      `(d,)` array for `(d,)` bounds); returns a scalar or any fixed-shape array.
    - `lo`, `hi`: the box, scalars or shape `(d,)`, with `lo < hi` (may be traced).
    - `n`: the number of intervals per axis, even (a static Python int).
    - `batched`: if True, `f` receives a batch of points (`(k, d)` or `(k,)`,
      `k <= chunk`) and returns `(k, ...)`.
    - `chunk`: the largest number of points evaluated at once.

    **Returns:** $\hat I$, an array with the shape of `f`'s output.

    **Raises:** `ValueError` if `n < 1` or odd, the bounds are malformed or
    `lo >= hi`, or the grid has more than `MAX_EVALUATIONS` points; `TypeError`
    if `n` is not an int or `f` is not callable.
    """
    return _tensor_rule(f, lo, hi, n, _simpson_rule, batched=batched, chunk=chunk, even=True)


def gauss_legendre(
    f: Callable,
    lo: Any,
    hi: Any,
    n: int,
    *,
    batched: bool = False,
    chunk: int = _DEFAULT_CHUNK,
) -> jax.Array:
    r"""Gauss–Legendre rule with $n$ points per axis.

    $$\hat I_G = \frac{b-a}{2}\sum_{i=1}^n w_i\, f\Big(\frac{a+b}{2} + \frac{b-a}{2}\xi_i\Big),$$

    with $\xi_i$ the roots of the Legendre polynomial $P_n$ and $w_i =
    2/\big((1-\xi_i^2) P_n'(\xi_i)^2\big)$ (from `numpy.polynomial.legendre.leggauss`
    at trace time). Exact for polynomials of degree $2n - 1$, the most any
    $n$-point rule achieves; the error is
    $\frac{(b-a)^{2n+1}(n!)^4}{(2n+1)((2n)!)^3} f^{(2n)}(\xi)$, which for
    analytic $f$ falls geometrically in $n$. With `(d,)` bounds, the tensor
    product (eq. 2) over $n^d$ points, exact for polynomials of degree
    $\le 2n-1$ in each variable.

    **Arguments:**

    - `f`: the integrand, written for one point (a scalar for scalar bounds, a
      `(d,)` array for `(d,)` bounds); returns a scalar or any fixed-shape array.
    - `lo`, `hi`: the box, scalars or shape `(d,)`, with `lo < hi` (may be traced).
    - `n`: the number of nodes per axis (a static Python int).
    - `batched`: if True, `f` receives a batch of points (`(k, d)` or `(k,)`,
      `k <= chunk`) and returns `(k, ...)`.
    - `chunk`: the largest number of points evaluated at once.

    **Returns:** $\hat I$, an array with the shape of `f`'s output.

    **Raises:** `ValueError` if `n < 1`, the bounds are malformed or
    `lo >= hi`, or the grid has more than `MAX_EVALUATIONS` points; `TypeError`
    if `n` is not an int or `f` is not callable.
    """
    return _tensor_rule(f, lo, hi, n, _gauss_legendre_rule, batched=batched, chunk=chunk)
