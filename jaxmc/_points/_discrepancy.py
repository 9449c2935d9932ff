r"""The centred and $L_2$-star `discrepancy` of a point set."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax import lax

from .._checks import check_choice


def _pairwise_sum(x: jax.Array, kernel) -> jax.Array:
    """$\\sum_{i,j} \\prod_k \\text{kernel}(x_{ik}, x_{jk})$ in row blocks of bounded memory."""
    n, d = x.shape
    block = max(1, min(n, 2**22 // max(1, n * d)))
    blocks = -(-n // block)
    padded = jnp.concatenate([x, jnp.zeros((blocks * block - n, d), x.dtype)], axis=0)
    valid = jnp.arange(blocks * block) < n

    def one(args):
        rows, mask = args
        terms = jnp.prod(kernel(rows[:, None, :], x[None, :, :]), axis=2)
        return jnp.sum(jnp.where(mask[:, None], terms, 0))

    parts = lax.map(one, (padded.reshape(blocks, block, d), valid.reshape(blocks, block)))
    return jnp.sum(parts)


@functools.partial(jax.jit, static_argnames=("method",))
def _discrepancy(x, method):
    n, d = x.shape
    if method == "CD":
        a = jnp.abs(x - 0.5)
        first = (13.0 / 12.0) ** d
        second = 2.0 / n * jnp.sum(jnp.prod(1 + 0.5 * a - 0.5 * a**2, axis=1))
        third = (
            _pairwise_sum(
                x,
                lambda u, v: (
                    1 + 0.5 * jnp.abs(u - 0.5) + 0.5 * jnp.abs(v - 0.5) - 0.5 * jnp.abs(u - v)
                ),
            )
            / n**2
        )
        return first - second + third
    first = 3.0 ** (-d)
    second = 2.0 ** (1 - d) / n * jnp.sum(jnp.prod(1 - x**2, axis=1))
    third = _pairwise_sum(x, lambda u, v: 1 - jnp.maximum(u, v)) / n**2
    return jnp.sqrt(first - second + third)


def discrepancy(x: jax.Array, *, method: str = "CD") -> jax.Array:
    r"""Discrepancy of a point set `x` of shape `(n, d)` in $[0,1]^d$ (lower is more uniform).

    - `"CD"`, the centred $L_2$ discrepancy (Hickernell 1998), **squared** as in SciPy:
      $$\left(\tfrac{13}{12}\right)^d - \tfrac{2}{n}\sum_i \prod_k \left(1 + \tfrac12|x_{ik} - \tfrac12| - \tfrac12|x_{ik} - \tfrac12|^2\right) + \tfrac{1}{n^2}\sum_{i,j}\prod_k\left(1 + \tfrac12|x_{ik}-\tfrac12| + \tfrac12|x_{jk}-\tfrac12| - \tfrac12|x_{ik}-x_{jk}|\right).$$
    - `"L2-star"`, the $L_2$-star discrepancy (Warnock's formula), as in SciPy:
      $$\left(3^{-d} - \tfrac{2^{1-d}}{n}\sum_i\prod_k (1 - x_{ik}^2) + \tfrac1{n^2}\sum_{i,j}\prod_k (1 - \max(x_{ik}, x_{jk}))\right)^{1/2}.$$

    Both equal `scipy.stats.qmc.discrepancy(x, method=...)`. The double sum costs
    $O(n^2 d)$ and is evaluated in row blocks of bounded memory.

    **Arguments:**

    - `x`: points, shape `(n, d)`.
    - `method`: `"CD"` or `"L2-star"`.

    **Returns:** a scalar.
    """
    method = check_choice(method, "method", ("CD", "L2-star"))
    x = jnp.asarray(x)
    if x.ndim != 2 or x.shape[0] < 1 or x.shape[1] < 1:
        raise ValueError(f"`x` must have shape (n, d) with n, d >= 1, got {x.shape}.")
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return _discrepancy(x, method)
