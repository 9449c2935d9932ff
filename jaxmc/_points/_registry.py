r"""One registry of named, randomised point sets on the open cube $(0,1)^d$.

The estimators (`randomized_qmc`'s `points`, the block methods of `integrate`)
and the renderer's per-pixel patterns look their names up here, so a name
means the same points everywhere. Each caller accepts its own subset of names.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import jax

from ._common import float_dtype, open_unit
from ._halton import halton
from ._lattice import lattice
from ._random_sets import latin_hypercube, stratified, uniform
from ._sobol import sobol


def _uniform(key, n, d, dtype, counts):
    return uniform(key, n, d, dtype=dtype)


def _jax_random_uniform(key, n, d, dtype, counts):
    # i.i.d. like "uniform", but from `jax.random`'s own stream (what the renderer draws).
    # `jax.random.uniform` can return 0: kept in the open cube like every other set.
    return open_unit(jax.random.uniform(key, (n, d), float_dtype(dtype)))


def _stratified(key, n, d, dtype, counts):
    if counts is None or len(counts) != d or math.prod(counts) != n:
        raise ValueError(
            f'the "stratified" point set needs `counts`, {d} strata per axis whose product '
            f"is n={n}, got counts={counts!r}."
        )
    return stratified(key, counts, dtype=dtype)


def _latin_hypercube(key, n, d, dtype, counts):
    return latin_hypercube(key, n, d, dtype=dtype)


def _halton(key, n, d, dtype, counts):
    return halton(n, d, key=key, dtype=dtype)


def _sobol(key, n, d, dtype, counts):
    return sobol(n, d, key=key, dtype=dtype)


def _lattice(key, n, d, dtype, counts):
    return lattice(n, d, key=key, dtype=dtype)


POINT_SETS: dict[str, Callable[..., jax.Array]] = {
    "uniform": _uniform,
    "jax_random_uniform": _jax_random_uniform,
    "stratified": _stratified,
    "latin_hypercube": _latin_hypercube,
    "halton": _halton,
    "sobol": _sobol,
    "lattice": _lattice,
}
"""Name -> `generate(key, n, d, dtype, counts)`, `n` randomised points of shape `(n, d)`."""


def unit_points(
    name: str,
    key: jax.Array,
    n: int,
    d: int,
    *,
    dtype=None,
    counts: tuple[int, ...] | None = None,
) -> jax.Array:
    r"""`n` points of the named set on $(0,1)^d$ (never on a face), randomised by `key`.

    Each randomised point is marginally uniform on $[0,1)^d$, so the
    equal-weight average of $f$ over the set is unbiased.

    **Arguments:**

    - `name`: a key of `POINT_SETS`: `"uniform"` (`jaxmc.points.uniform`),
      `"jax_random_uniform"` (i.i.d. from `jax.random.uniform`), `"stratified"`,
      `"latin_hypercube"`, `"halton"`, `"sobol"` or `"lattice"` (the functions of
      `jaxmc.points` of those names, randomised by `key`).
    - `key`: a PRNG key.
    - `n`, `d`: number of points and dimension (static ints).
    - `dtype`: floating dtype of the points (default: JAX's default float).
    - `counts`: strata per axis of `"stratified"` (`d` entries with product `n`);
      the other sets ignore it.

    **Returns:** an array of shape `(n, d)`.
    """
    if not isinstance(name, str) or name not in POINT_SETS:
        raise ValueError(f"`name` must be one of {tuple(POINT_SETS)}, got {name!r}.")
    return POINT_SETS[name](key, n, d, dtype, counts)
