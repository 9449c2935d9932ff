r"""Deterministic quadrature baselines (Davis & Rabinowitz, *Methods of Numerical
Integration*, 2nd ed., 1984).

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
any dimension (Owen, *Monte Carlo theory, methods and examples*, ch. 2).
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

# Only the API is public here: the annotations' names are imported privately,
# and the limit is read at call time, so lowering `quad.MAX_EVALUATIONS` takes effect.
from collections.abc import Callable as _Callable
from typing import Any as _Any

import jax as _jax

from ._quad import (
    _gauss_legendre_rule,
    _midpoint_rule,
    _simpson_rule,
    _tensor_rule,
    _trapezoid_rule,
)


__all__ = ["MAX_EVALUATIONS", "gauss_legendre", "midpoint", "simpson", "trapezoid"]

#: The largest tensor grid (number of integrand evaluations) a rule will evaluate.
MAX_EVALUATIONS = 2**27

_DEFAULT_CHUNK = 2**16


def midpoint(
    f: _Callable,
    lo: _Any,
    hi: _Any,
    n: int,
    *,
    batched: bool = False,
    chunk: int = _DEFAULT_CHUNK,
    args: _Any = None,
) -> _jax.Array:
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
    - `args`: parameters passed as `f(x, args)` when given; new values of the
      same shapes reuse the compiled code.

    **Returns:** $\hat I$, an array with the shape of `f`'s output.

    **Raises:** `ValueError` if `n < 1`, the bounds are malformed or
    `lo >= hi`, or the grid has more than `MAX_EVALUATIONS` points; `TypeError`
    if `n` is not an int or `f` is not callable.
    """
    return _tensor_rule(
        f, lo, hi, n, _midpoint_rule, batched=batched, chunk=chunk, limit=MAX_EVALUATIONS,
        args=args,
    )


def trapezoid(
    f: _Callable,
    lo: _Any,
    hi: _Any,
    n: int,
    *,
    batched: bool = False,
    chunk: int = _DEFAULT_CHUNK,
    args: _Any = None,
) -> _jax.Array:
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
    - `args`: parameters passed as `f(x, args)` when given; new values of the
      same shapes reuse the compiled code.

    **Returns:** $\hat I$, an array with the shape of `f`'s output.

    **Raises:** `ValueError` if `n < 1`, the bounds are malformed or
    `lo >= hi`, or the grid has more than `MAX_EVALUATIONS` points; `TypeError`
    if `n` is not an int or `f` is not callable.
    """
    return _tensor_rule(
        f, lo, hi, n, _trapezoid_rule, batched=batched, chunk=chunk, limit=MAX_EVALUATIONS,
        args=args,
    )


def simpson(
    f: _Callable,
    lo: _Any,
    hi: _Any,
    n: int,
    *,
    batched: bool = False,
    chunk: int = _DEFAULT_CHUNK,
    args: _Any = None,
) -> _jax.Array:
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
    - `args`: parameters passed as `f(x, args)` when given; new values of the
      same shapes reuse the compiled code.

    **Returns:** $\hat I$, an array with the shape of `f`'s output.

    **Raises:** `ValueError` if `n < 1` or odd, the bounds are malformed or
    `lo >= hi`, or the grid has more than `MAX_EVALUATIONS` points; `TypeError`
    if `n` is not an int or `f` is not callable.
    """
    return _tensor_rule(
        f, lo, hi, n, _simpson_rule, batched=batched, chunk=chunk, limit=MAX_EVALUATIONS,
        even=True, args=args,
    )


def gauss_legendre(
    f: _Callable,
    lo: _Any,
    hi: _Any,
    n: int,
    *,
    batched: bool = False,
    chunk: int = _DEFAULT_CHUNK,
    args: _Any = None,
) -> _jax.Array:
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
    - `args`: parameters passed as `f(x, args)` when given; new values of the
      same shapes reuse the compiled code.

    **Returns:** $\hat I$, an array with the shape of `f`'s output.

    **Raises:** `ValueError` if `n < 1`, the bounds are malformed or
    `lo >= hi`, or the grid has more than `MAX_EVALUATIONS` points; `TypeError`
    if `n` is not an int or `f` is not callable.
    """
    return _tensor_rule(
        f, lo, hi, n, _gauss_legendre_rule, batched=batched, chunk=chunk, limit=MAX_EVALUATIONS,
        args=args,
    )
