"""Helpers shared by the point sets: dtypes, the x64 switch, 32-bit words to floats in $(0, 1)$."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_count


# The shipped tables (Sobol' direction numbers, lattice generating vector).
DATA_DIR = Path(__file__).parent.parent / "_data"


def float_dtype(dtype: Any) -> np.dtype:
    """`dtype` as a NumPy dtype (JAX's default float for `None`); it must be floating."""
    dt = jnp.dtype(dtype) if dtype is not None else jnp.dtype(jnp.result_type(float))
    if not jnp.issubdtype(dt, jnp.floating):
        raise TypeError(f"`dtype` must be a floating dtype, got {dt}.")
    return dt


def below_one(dtype: Any) -> float:
    """The largest float of `dtype` below 1 (rounding must never produce 1)."""
    return float(np.nextafter(np.array(1.0, dtype=dtype), np.array(0.0, dtype=dtype)))


def open_unit(x: jax.Array) -> jax.Array:
    r"""Points of $[0, 1]$ clipped into the open interval: $[2^{-p}, 1 - 2^{-p}]$.

    $1 - 2^{-p}$ is the largest float below 1 ($p = 24$ in float32, 53 in
    float64), and the lower end mirrors it, so $1 - u$ stays inside too and an
    integrand singular at both ends (an inverse normal CDF) meets both alike.
    Only values within $2^{-p}$ of an end move, by less than $2^{-p}$: the
    strata of a net (intervals of width $\ge 2^{1-p}$) keep their points.
    """
    top = below_one(x.dtype)
    return jnp.clip(x, x.dtype.type(1.0 - top), x.dtype.type(top))


def x64_enabled() -> bool:
    """Whether `jax_enable_x64` is on, i.e. 64-bit integers and floats exist under `jit`."""
    return bool(jax.config.read("jax_enable_x64"))


def uint32_to_unit(x: jax.Array, dtype: np.dtype, centred: bool = False) -> jax.Array:
    r"""Map 32-bit integers $x$ to $x / 2^{32}$ in `dtype`, in the open interval $(0, 1)$.

    In float64 this is exact; in float32 (24-bit mantissa) the integer is
    truncated to its top 24 bits first, so the result never rounds up to 1.
    The one value that would be 0 ($x < 2^{32-p}$) becomes $2^{-p}$ (`open_unit`),
    still inside every elementary interval of width $2^{1-p}$ or more that held it.

    `centred` maps to the centre of the cell instead, $(x + 1/2) / 2^{32}$
    (float32: $(\lfloor x / 2^9 \rfloor + 1/2) / 2^{23}$, exact in 24 bits), for
    randomised points: a random digital shift makes $x$ uniform on the $2^{32}$
    cells, so $x / 2^{32}$ averages $f$ at the cells' left ends, a bias of
    $2^{-33} \sum_i \int (f|_{u_i=0} - f|_{u_i=1})$: an offset common to all replicas,
    which their spread does not see, and which on large nets can exceed QMC's own error;
    the centre's is $O(2^{-64})$.
    """
    if centred:  # strictly inside (0, 1) as it stands
        bits = min(32, jnp.finfo(dtype).nmant)
        kept = (x >> np.uint32(32 - bits)).astype(dtype)
        return (kept + dtype.type(0.5)) * dtype.type(2.0**-bits)
    if jnp.finfo(dtype).nmant >= 32:
        return open_unit(x.astype(dtype) * dtype.type(2.0**-32))
    shift = 32 - (jnp.finfo(dtype).nmant + 1)
    return open_unit((x >> np.uint32(shift)).astype(dtype) * dtype.type(2.0 ** -(32 - shift)))


def check_skip(skip: Any) -> int:
    """The index of the first point of a sequence: a static int `>= 0`."""
    return check_count(skip, "skip", minimum=0)
