r"""The box $[lo, hi]$: mapping the unit cube onto it and its volume, in one place.

Every sampler that draws on the unit cube and every density normalised on the
box goes through these, so the affine map $x = lo + (hi - lo)\,u$ and the
log-volume $\sum_j \log(hi_j - lo_j)$ are written once.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def to_box(u: jax.Array, lo: jax.Array, hi: jax.Array) -> jax.Array:
    r"""$lo + (hi - lo)\,u$: points of the unit cube mapped onto the box (broadcasting)."""
    return lo + (hi - lo) * u


def log_volume(lo: jax.Array, hi: jax.Array) -> jax.Array:
    r"""$\log \prod_j (hi_j - lo_j)$, summed in log space (no overflow in high dimensions)."""
    return jnp.sum(jnp.log(hi - lo))


def as_vectors(lo: jax.Array, hi: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The bounds as `(d,)` vectors (scalar bounds are `d = 1`)."""
    d = 1 if jnp.ndim(lo) == 0 else jnp.shape(lo)[0]
    return jnp.reshape(lo, (d,)), jnp.reshape(hi, (d,))
