r"""The box $[lo, hi]$: mapping the unit cube into it and its volume, in one place.

Every sampler that draws on the unit cube and every density normalised on the
box goes through these, so the affine map $x = lo + (hi - lo)\,u$ and the
log-volume $\sum_j \log(hi_j - lo_j)$ are written once.

Samples lie in the *open* box: rounding in $lo + (hi - lo)\,u$ can land on a
face ($hi$ for $u$ just below 1 in float32, $lo$ when $lo$ is large), where an
integrable endpoint singularity ($1/\sqrt{x}$, an inverse normal CDF) is
infinite. `to_box` and `clip_to_open_box` move such points to the nearest float
inside; `affine_to_box` is the exact map, for edges and corners that belong on
the faces.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def _step_inside(face: jax.Array, toward: jax.Array) -> jax.Array:
    """The float next to `face` in the direction of `toward`, never subnormal.

    CPUs flush subnormals to zero, so the neighbour of a face at 0 is the
    smallest normal float (of the right sign) instead.
    """
    step = jnp.nextafter(face, toward)
    tiny = jnp.asarray(jnp.finfo(step.dtype).tiny, step.dtype)
    return jnp.where(jnp.abs(step) < tiny, jnp.where(toward > face, tiny, -tiny), step)


def open_box(lo: jax.Array, hi: jax.Array) -> tuple[jax.Array, jax.Array]:
    r"""The innermost floats $[lo^+, hi^-]$ of the box: the neighbours of its faces inside it.

    A box with no float strictly between `lo` and `hi` (one ulp wide) has no
    interior; it gives $lo^+ = hi$, $hi^- = lo$. Not differentiable (the
    neighbours of a face are constant between floats).
    """
    lo, hi = jax.lax.stop_gradient(lo), jax.lax.stop_gradient(hi)
    return _step_inside(lo, hi), _step_inside(hi, lo)


@jax.custom_jvp
def _nudge(x: jax.Array, lower: jax.Array, upper: jax.Array) -> jax.Array:
    # Selects, not max/min: XLA's NaN-propagating float max/min vectorise worse on the CPU.
    return jnp.where(x < lower, lower, jnp.where(x > upper, upper, x))


@_nudge.defjvp
def _nudge_jvp(primals, tangents):
    # The nudge only undoes rounding, so a point's derivative is that of the exact map.
    x, lower, upper = primals
    return _nudge(x, lower, upper), tangents[0]


def clip_to_open_box(x: jax.Array, lo: jax.Array, hi: jax.Array) -> jax.Array:
    r"""Points `x` (broadcasting against `lo`, `hi`) clipped into $[lo^+, hi^-]$ (`open_box`).

    For points a map sends into $[lo, hi]$ up to rounding: a point on (or past)
    a face moves to the nearest float inside, every other point is unchanged,
    and derivatives pass through unchanged (those of the map).
    """
    x = jnp.asarray(x)
    dtype = x.dtype if jnp.issubdtype(x.dtype, jnp.floating) else jnp.result_type(float)
    lower, upper = open_box(jnp.asarray(lo, dtype), jnp.asarray(hi, dtype))
    return _nudge(x.astype(dtype), lower, upper)


def to_box(u: jax.Array, lo: jax.Array, hi: jax.Array) -> jax.Array:
    r"""$lo + (hi - lo)\,u$: points of the unit cube mapped into the open box (broadcasting).

    Rounding onto a face is undone by `clip_to_open_box`, so no sample lies on one.
    """
    return clip_to_open_box(affine_to_box(u, lo, hi), lo, hi)


def affine_to_box(t: jax.Array, lo: jax.Array, hi: jax.Array) -> jax.Array:
    r"""$lo + (hi - lo)\,t$ as rounded, faces included: for edges and corners, not samples."""
    return lo + (hi - lo) * t


def log_volume(lo: jax.Array, hi: jax.Array) -> jax.Array:
    r"""$\log \prod_j (hi_j - lo_j)$, summed in log space (no overflow in high dimensions)."""
    return jnp.sum(jnp.log(hi - lo))


def as_vectors(lo: jax.Array, hi: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The bounds as `(d,)` vectors (scalar bounds are `d = 1`)."""
    d = 1 if jnp.ndim(lo) == 0 else jnp.shape(lo)[0]
    return jnp.reshape(lo, (d,)), jnp.reshape(hi, (d,))
