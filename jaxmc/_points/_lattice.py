r"""Rank-1 lattices with the Cools–Kuo–Nuyens generating vector, optionally randomly shifted."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_count, check_key
from ._common import DATA_DIR, float_dtype, open_unit, x64_enabled


@functools.cache
def _lattice_vector() -> np.ndarray:
    lines = (DATA_DIR / "lattice_kuo_order2.txt").read_text().splitlines()
    return np.array([int(s) for s in lines if s and not s.startswith("#")], dtype=np.int64)


LATTICE_MAX_DIM: int = 100
"""Largest dimension `lattice` supports (the shipped generating vector has 100 components)."""


@functools.partial(jax.jit, static_argnames=("n", "d", "dtype"))
def _lattice(key, n, d, dtype):
    z = _lattice_vector()[:d] % n
    if n & (n - 1) == 0:
        # i z mod 2^32 wraps, and 2^32 is a multiple of n.
        i = jnp.arange(n, dtype=jnp.uint32)[:, None]
        k = (i * jnp.asarray(z, jnp.uint32)[None, :]) & np.uint32(n - 1)
    elif x64_enabled():
        i = jnp.arange(n, dtype=jnp.int64)[:, None]
        k = (i * jnp.asarray(z, jnp.int64)[None, :]) % n
    else:
        i = jnp.arange(n, dtype=jnp.uint32)[:, None]
        k = (i * jnp.asarray(z, jnp.uint32)[None, :]) % np.uint32(n)
    acc = np.dtype(jnp.float64 if x64_enabled() else dtype)
    x = k.astype(acc) / acc.type(n)  # XLA may use a reciprocal: exact only for powers of two
    if key is not None:
        x = x + jax.random.uniform(key, (d,), dtype=acc)[None, :]
        x = jnp.where(x >= 1, x - 1, x)
    return open_unit(x.astype(dtype))


def lattice(n: int, d: int, *, key: jax.Array | None = None, dtype=None) -> jax.Array:
    r"""Rank-1 lattice $x_i = \{ i z / n \}$, $i = 0, \dots, n-1$; with `key`, randomly shifted.

    The generating vector $z$ is the order-2 embedded (extensible) lattice
    sequence `lattice-32001-1024-1048576.3600` of Cools, Kuo & Nuyens (2006),
    constructed by component-by-component search for $n = 2^{10}, \dots, 2^{20}$
    (first 100 components shipped; see `_data/README.md`). For powers of two the
    point sets are nested, for other `n` it is still a valid lattice but its
    quality is not guaranteed.

    With `key`, a single uniform shift $\Delta \sim \mathcal U[0,1)^d$ is added
    modulo 1, $x_i = \{ i z / n + \Delta \}$ (Cranley & Patterson 1976): each point
    is uniform on $[0,1)^d$ and the lattice structure is kept.

    Points lie in the open cube $(0, 1)^d$: a coordinate 0 (the first point of
    an unshifted lattice) is returned as $2^{-p}$, and one that rounds up to 1
    in the output dtype as $1 - 2^{-p}$ ($p$ the dtype's precision).

    **Arguments:**

    - `n`: number of points (static int `>= 1`; a power of two up to `2**20` is best).
      Non-powers of two above `2**16` need `jax_enable_x64`.
    - `d`: dimension, `1 <= d <= LATTICE_MAX_DIM` (100).
    - `key`: a PRNG key for the random shift, or `None`.
    - `dtype`: floating dtype of the result.

    **Returns:** an array of shape `(n, d)` in $(0,1)^d$.
    """
    n = check_count(n, "n")
    d = check_count(d, "d")
    if d > LATTICE_MAX_DIM:
        raise ValueError(f"`d` must be <= {LATTICE_MAX_DIM} for `lattice`, got {d}.")
    if n > 2**32:
        raise ValueError(f"`n` must be <= 2**32 for `lattice`, got {n}.")
    if n & (n - 1) and not x64_enabled() and n > 2**16:
        raise ValueError(
            f"`n` = {n} is not a power of two; without jax_enable_x64 only n <= 2**16 "
            "is supported (the products i*z need 64 bits)."
        )
    if key is not None:
        key = check_key(key)
    return _lattice(key, n, d, float_dtype(dtype))

