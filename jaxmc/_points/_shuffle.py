r"""Fisher–Yates `shuffle` of the rows of an array."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

from .._checks import check_key


@jax.jit
def _fisher_yates(key, x):
    n = x.shape[0]
    # j_i uniform on {0..i} for i = n-1 .. 1 (drawn up front; the loop only swaps).
    upper = jnp.arange(1, n + 1, dtype=jnp.int32)
    js = jax.random.randint(key, (n,), 0, upper, dtype=jnp.int32)

    def body(t, perm):
        i = n - 1 - t
        j = js[i]
        pi, pj = perm[i], perm[j]
        return perm.at[i].set(pj).at[j].set(pi)

    perm = lax.fori_loop(0, n - 1, body, jnp.arange(n, dtype=jnp.int32))
    return jnp.take(x, perm, axis=0)


def shuffle(key: jax.Array, x: jax.Array) -> jax.Array:
    r"""Shuffle `x` along axis 0 with the Fisher–Yates algorithm.

    For $i = n-1, \dots, 1$: draw $j$ uniform on $\{0, \dots, i\}$ and swap
    entries $i$ and $j$ (Durstenfeld 1964; Knuth's Algorithm P). Each of the $n!$
    permutations has probability $1/n!$. The swaps run in a `lax.fori_loop` on
    an index array (so the loop is $O(n)$ whatever the row size), then the rows are
    gathered once.

    **Arguments:**

    - `key`: a PRNG key.
    - `x`: an array with at least one axis.

    **Returns:** an array like `x` with its rows permuted.
    """
    key = check_key(key)
    x = jnp.asarray(x)
    if x.ndim == 0:
        raise ValueError("`x` must have at least one axis to shuffle, got a scalar.")
    if x.shape[0] >= 2**31:
        raise ValueError(f"`x` must have fewer than 2**31 rows, got {x.shape[0]}.")
    if x.shape[0] <= 1:
        return x
    return _fisher_yates(key, x)

