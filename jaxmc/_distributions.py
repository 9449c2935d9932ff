"""Tabulated densities and rejection sampling: the implementation of `jaxmc.distributions`."""

from __future__ import annotations

import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from ._checks import check_callable, check_count, check_key, is_concrete


# ---------------------------------------------------------------------------
# tabulation helpers


def _check_values(values: ArrayLike, ndim: int) -> jax.Array:
    values = jnp.asarray(values)
    if not jnp.issubdtype(values.dtype, jnp.floating):
        values = values.astype(jnp.result_type(float))
    if values.ndim != ndim or values.size == 0:
        shape = "(n,)" if ndim == 1 else "(ny, nx)"
        raise ValueError(
            f"`values` must be a non-empty array of shape {shape}, got shape {values.shape}."
        )
    if is_concrete(values):
        v = np.asarray(values)
        if not np.all(np.isfinite(v)):
            raise ValueError("`values` must be finite, got non-finite entries.")
        if np.any(v < 0):
            raise ValueError(f"`values` must be >= 0 (a density), got minimum {v.min()}.")
        if not np.any(v > 0):
            raise ValueError("`values` must not be all zero: there is nothing to sample.")
    return values


def _check_box(lo: ArrayLike, hi: ArrayLike, shape: tuple[int, ...], dtype) -> tuple:
    lo = jnp.asarray(lo, dtype=dtype)
    hi = jnp.asarray(hi, dtype=dtype)
    for name, v in (("lo", lo), ("hi", hi)):
        if v.shape != shape:
            raise ValueError(f"`{name}` must have shape {shape}, got {v.shape}.")
    if is_concrete(lo) and is_concrete(hi):
        lo_np, hi_np = np.asarray(lo), np.asarray(hi)
        if not (np.all(np.isfinite(lo_np)) and np.all(np.isfinite(hi_np)) and np.all(lo_np < hi_np)):
            raise ValueError(f"`lo` must be < `hi` and both finite, got lo={lo_np}, hi={hi_np}.")
    return lo, hi


def _tabulate(values: jax.Array, width: jax.Array) -> tuple[jax.Array, jax.Array]:
    """CDF table(s) along the last axis and the integral(s) $\\sum_i v_i\\,\\Delta$.

    The CDF at the cell edges, $P_0 = 0$, $P_i = \\sum_{j<i} v_j / \\sum_j v_j$,
    $P_n = 1$ exactly. A row that is all zero (never selected by a marginal)
    gets a uniform CDF instead of 0/0.
    """
    n = values.shape[-1]
    cum = jnp.cumsum(values, axis=-1)
    total = cum[..., -1:]
    uniform = jnp.arange(1, n + 1, dtype=values.dtype) / n
    cdf = jnp.where(total > 0, cum / jnp.where(total > 0, total, 1.0), uniform)
    cdf = cdf.at[..., -1].set(1.0)
    zero = jnp.zeros(values.shape[:-1] + (1,), values.dtype)
    return jnp.concatenate([zero, cdf], axis=-1), total[..., 0] * width


def _invert(cdf: jax.Array, u: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Cell index $i$ with $P_i \\le u < P_{i+1}$ and the offset $t \\in [0, 1]$ within it.

    `searchsorted(..., side="right")` skips cells of zero probability (where
    $P_i = P_{i+1}$), so a sample never lands in a cell whose density is 0.
    """
    n = cdf.shape[-1] - 1
    if cdf.ndim == 1:
        idx = jnp.searchsorted(cdf, u, side="right") - 1
    else:  # one CDF row per sample
        search = functools.partial(jnp.searchsorted, side="right")
        idx = jnp.vectorize(search, signature="(m),()->()")(cdf, u) - 1
    idx = jnp.clip(idx, 0, n - 1)
    take = (lambda a, i: a[i]) if cdf.ndim == 1 else (
        lambda a, i: jnp.take_along_axis(a, i[..., None], axis=-1)[..., 0]
    )
    c0, c1 = take(cdf, idx), take(cdf, idx + 1)
    step = c1 - c0
    t = jnp.where(step > 0, (u - c0) / jnp.where(step > 0, step, 1.0), 0.0)
    return idx, jnp.clip(t, 0.0, 1.0)


def _locate(x: jax.Array, lo: jax.Array, hi: jax.Array, n: int):
    """Cell index of `x` in `n` equal cells of $[lo, hi]$, and whether `x` is inside."""
    inside = (x >= lo) & (x <= hi)
    idx = jnp.floor((x - lo) / (hi - lo) * n).astype(jnp.int32)
    return jnp.clip(idx, 0, n - 1), inside


# ---------------------------------------------------------------------------
# Piecewise1D


class Piecewise1D(eqx.Module):
    r"""Piecewise-constant density on $[lo, hi]$ proportional to `values` (PBRT 3rd ed. §13.3.1).

    With $n$ cells of width $\Delta = (hi - lo)/n$ and $f(x) = v_i$ on cell $i$,
    the density is $p(x) = v_i / I$ with $I = \sum_i v_i \Delta$ (`integral`).
    Its CDF is piecewise linear through $P(lo + i\Delta) = \sum_{j<i} v_j /
    \sum_j v_j$, so the inversion $X = P^{-1}(U)$ (PBRT 3rd ed. §13.3.1) is a binary
    search for the cell and a linear interpolation inside it. Cells with
    $v_i = 0$ are never sampled.

    Under `jit` and `grad` this is an ordinary pytree: `values`, `lo` and `hi`
    are arrays, and `sample` is differentiable in `values` (the sample moves
    with the CDF).

    !!! Example

        ```python
        d = jaxmc.distributions.Piecewise1D(jnp.array([1.0, 3.0]), 0.0, 2.0)
        x, p = d.sample(jax.random.uniform(key, (1000,)))  # p = 0.25 or 0.75
        ```
    """

    values: jax.Array
    lo: jax.Array
    hi: jax.Array
    cdf_table: jax.Array
    integral: jax.Array

    def __init__(self, values: ArrayLike, lo: ArrayLike = 0.0, hi: ArrayLike = 1.0):
        """**Arguments:**

        - `values`: shape `(n,)`, non-negative, finite, not all zero; the
          (unnormalised) function value on each of `n` equal cells.
        - `lo`, `hi`: scalar bounds of the support, `lo < hi`.
        """
        values = _check_values(values, 1)
        lo, hi = _check_box(lo, hi, (), values.dtype)
        self.values = values
        self.lo, self.hi = lo, hi
        self.cdf_table, self.integral = _tabulate(values, (hi - lo) / values.shape[0])

    @property
    def size(self) -> int:
        """Number of cells."""
        return self.values.shape[0]

    def sample(self, u: ArrayLike) -> tuple[jax.Array, jax.Array]:
        """Warp uniform `u` (a scalar or any batch shape) to `(x, pdf)` of the same shape."""
        u = jnp.asarray(u)
        if not jnp.issubdtype(u.dtype, jnp.floating):
            raise TypeError(f"`u` must be floating uniform variates, got dtype {u.dtype}.")
        idx, t = _invert(self.cdf_table, u)
        width = (self.hi - self.lo) / self.size
        x = self.lo + (idx.astype(t.dtype) + t) * width
        return x, self.values[idx] / self.integral

    def pdf(self, x: ArrayLike) -> jax.Array:
        """Density $v_i / I$ at `x` (any shape), 0 outside $[lo, hi]$."""
        x = jnp.asarray(x)
        idx, inside = _locate(x, self.lo, self.hi, self.size)
        return jnp.where(inside, self.values[idx] / self.integral, 0.0)

    def cdf(self, x: ArrayLike) -> jax.Array:
        """The CDF $P(x)$ (piecewise linear), 0 below `lo` and 1 above `hi`."""
        x = jnp.asarray(x)
        idx, _ = _locate(x, self.lo, self.hi, self.size)
        width = (self.hi - self.lo) / self.size
        t = jnp.clip((x - self.lo) / width - idx.astype(x.dtype), 0.0, 1.0)
        c0, c1 = self.cdf_table[idx], self.cdf_table[idx + 1]
        return jnp.where(x < self.lo, 0.0, jnp.where(x > self.hi, 1.0, c0 + t * (c1 - c0)))


# ---------------------------------------------------------------------------
# Piecewise2D


class Piecewise2D(eqx.Module):
    r"""Piecewise-constant density on a rectangle, proportional to an image `values`.

    `values[j, i]` is the function on the cell in row $j$ (the $y$ axis) and
    column $i$ (the $x$ axis), like an image or an environment map. The density
    is $p(x, y) = v_{ji} / I$ with $I = \sum_{ji} v_{ji} \Delta_x \Delta_y$
    (`integral`). Sampling factors it as $p(x, y) = p(y)\,p(x \mid y)$ and
    inverts both CDFs (PBRT 3rd ed. §13.3.1): the marginal $p(y) \propto \sum_i v_{ji}$
    picks the row from `u[..., 1]`, the row's conditional picks $x$ from
    `u[..., 0]` (PBRT's `Distribution2D`). For a latitude-longitude
    environment map, multiply `values` by $\sin\theta$ of each row first and
    divide the pdf by $2\pi^2 \sin\theta$ to get a solid-angle density.
    """

    values: jax.Array
    lo: jax.Array
    hi: jax.Array
    marginal_cdf: jax.Array
    conditional_cdf: jax.Array
    integral: jax.Array

    def __init__(
        self, values: ArrayLike, lo: ArrayLike = (0.0, 0.0), hi: ArrayLike = (1.0, 1.0)
    ):
        """**Arguments:**

        - `values`: shape `(ny, nx)`, non-negative, finite, not all zero.
        - `lo`, `hi`: shape `(2,)`, the corners $(x_0, y_0)$ and $(x_1, y_1)$.
        """
        values = _check_values(values, 2)
        lo, hi = _check_box(lo, hi, (2,), values.dtype)
        ny, nx = values.shape
        dx = (hi[0] - lo[0]) / nx
        dy = (hi[1] - lo[1]) / ny
        self.values = values
        self.lo, self.hi = lo, hi
        self.conditional_cdf, row_integrals = _tabulate(values, dx)
        self.marginal_cdf, self.integral = _tabulate(row_integrals, dy)

    @property
    def shape(self) -> tuple[int, int]:
        """`(ny, nx)`."""
        return self.values.shape

    def sample(self, u: ArrayLike) -> tuple[jax.Array, jax.Array]:
        """Warp `u` of shape `(..., 2)` to `(xy, pdf)`, `xy` of shape `(..., 2)` as `(x, y)`."""
        u = jnp.asarray(u)
        if u.ndim == 0 or u.shape[-1] != 2:
            raise ValueError(f"`u` must have shape (..., 2), got {u.shape}.")
        if not jnp.issubdtype(u.dtype, jnp.floating):
            raise TypeError(f"`u` must be floating uniform variates, got dtype {u.dtype}.")
        ny, nx = self.shape
        iy, ty = _invert(self.marginal_cdf, u[..., 1])
        ix, tx = _invert(self.conditional_cdf[iy], u[..., 0])
        cell = (self.hi - self.lo) / jnp.asarray([nx, ny], self.values.dtype)
        index = jnp.stack([ix.astype(tx.dtype) + tx, iy.astype(ty.dtype) + ty], axis=-1)
        lo, cell = jnp.broadcast_to(self.lo, index.shape), jnp.broadcast_to(cell, index.shape)
        xy = lo + index * cell
        return xy, self.values[iy, ix] / self.integral

    def pdf(self, xy: ArrayLike) -> jax.Array:
        """Density at `xy` of shape `(..., 2)`, 0 outside the rectangle."""
        xy = jnp.asarray(xy)
        if xy.ndim == 0 or xy.shape[-1] != 2:
            raise ValueError(f"`xy` must have shape (..., 2), got {xy.shape}.")
        ny, nx = self.shape
        ix, in_x = _locate(xy[..., 0], self.lo[0], self.hi[0], nx)
        iy, in_y = _locate(xy[..., 1], self.lo[1], self.hi[1], ny)
        return jnp.where(in_x & in_y, self.values[iy, ix] / self.integral, 0.0)


# ---------------------------------------------------------------------------
# rejection (PBRT 3rd ed. §13.3.2)


def rejection(
    key: jax.Array,
    n: int,
    propose: Callable[[jax.Array, int], jax.Array],
    accept: Callable[[jax.Array, jax.Array], jax.Array],
    *,
    max_rounds: int = 32,
    batch_size: int | None = None,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    r"""Rejection sampling (PBRT 3rd ed. §13.3.2) in fixed shapes, so it works under `jit`.

    Each round proposes `batch_size` candidates (default `n`) with
    `propose(key, m)` and keeps those where `accept(key, x)` is True, filling
    the `n` output slots in order; it stops when all slots are full or after
    `max_rounds` rounds (a `lax.while_loop`, sizes static). The accepted
    points have the proposal's law restricted to the acceptance region, and
    the fraction accepted estimates the efficiency, (area of the region) ÷
    (area of the proposal's support) for uniform proposals.

    Keys: round $r$ uses `jax.random.fold_in(key, r)`, split into a
    proposal key and an acceptance key.

    **Arguments:**

    - `key`: a PRNG key.
    - `n`: number of samples wanted (static).
    - `propose`: `propose(key, m) -> x` of shape `(m, ...)`.
    - `accept`: `accept(key, x) -> bool` of shape `(m,)`; use the key for
      probabilistic acceptance ($u < f(x)/(M g(x))$), or ignore it for a region.
    - `max_rounds`: maximum number of proposal rounds (static).
    - `batch_size`: candidates per round (static), default `n`.

    **Returns:** `(x, accepted_mask, acceptance_rate)`: `x` of shape
    `(n, ...)`; `accepted_mask` of shape `(n,)`, False for slots left empty
    (zeros) when `max_rounds` ran out; `acceptance_rate`, accepted ÷ proposed
    over all rounds run.
    """
    key = check_key(key)
    n = check_count(n, "n")
    max_rounds = check_count(max_rounds, "max_rounds")
    m = n if batch_size is None else check_count(batch_size, "batch_size")
    check_callable(propose, "propose")
    check_callable(accept, "accept")

    x_spec = jax.eval_shape(lambda k: propose(k, m), key)
    if not hasattr(x_spec, "shape") or x_spec.ndim == 0 or x_spec.shape[0] != m:
        raise ValueError(
            f"`propose(key, m)` must return one array with leading axis m={m}, got {x_spec}."
        )
    a_spec = jax.eval_shape(accept, key, x_spec)
    if not hasattr(a_spec, "shape") or a_spec.shape != (m,):
        raise ValueError(f"`accept(key, x)` must return shape ({m},), got {a_spec}.")
    if a_spec.dtype != jnp.bool_:
        raise TypeError(f"`accept(key, x)` must return booleans, got dtype {a_spec.dtype}.")

    def cond(state):
        _, filled, _, _, r = state
        return (filled < n) & (r < max_rounds)

    def body(state):
        out, filled, proposed, accepted, r = state
        key_proposal, key_accept = jax.random.split(jax.random.fold_in(key, r))
        x = propose(key_proposal, m)
        ok = accept(key_accept, x)
        slot = filled + jnp.cumsum(ok, dtype=jnp.int32) - 1
        slot = jnp.where(ok & (slot < n), slot, n)  # index n is out of bounds: dropped
        out = out.at[slot].set(x, mode="drop")
        count = jnp.sum(ok, dtype=jnp.int32)
        return out, jnp.minimum(filled + count, n), proposed + m, accepted + count, r + 1

    zero = jnp.zeros((), jnp.int32)
    init = (jnp.zeros((n,) + x_spec.shape[1:], x_spec.dtype), zero, zero, zero, zero)
    out, filled, proposed, accepted, _ = jax.lax.while_loop(cond, body, init)
    dtype = jnp.result_type(float)
    rate = accepted.astype(dtype) / proposed.astype(dtype)
    return out, jnp.arange(n, dtype=jnp.int32) < filled, rate


def disk_rejection(
    key: jax.Array, n: int, *, max_rounds: int = 32
) -> tuple[jax.Array, jax.Array, jax.Array]:
    r"""Uniform points on the unit disk by rejection from $[-1, 1]^2$ (PBRT 3rd ed. §13.3.2).

    Propose uniformly on the square and keep points with $x^2 + y^2 < 1$; the
    efficiency is $\pi r^2 / 4 r^2 = \pi/4 \approx 78.5\%$. Returns
    `(x, accepted_mask, acceptance_rate)` as `rejection`.
    """

    def propose(k, m):
        return jax.random.uniform(k, (m, 2), minval=-1.0, maxval=1.0)

    def accept(_, x):
        return jnp.sum(x * x, axis=-1) < 1.0

    return rejection(key, n, propose, accept, max_rounds=max_rounds)
