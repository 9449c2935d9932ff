"""The sample spaces `chi2_test` knows, each with a 1-D or 2-D parameterisation whose
grid of cells the histogram and the quadrature share."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._warps._sphere import spherical_direction


_DOMAINS = ("square", "disk", "sphere", "hemisphere", "triangle")
# Relative slack when deciding whether a sample lies in the domain (rounding).
_EPS = 1e-5


@dataclass(frozen=True)
class _Domain:
    """A parameterisation `p in [lo, hi]` (1-D or 2-D) of the sample space.

    `forward(p) -> (x, jacobian)` maps parameters to points with the density of
    the natural measure (`dx = jacobian dp`); `backward(x) -> (p, inside)`.
    """

    lo: np.ndarray
    hi: np.ndarray
    point_shape: tuple[int, ...]
    forward: Callable[[jax.Array], tuple[jax.Array, jax.Array]]
    backward: Callable[[jax.Array], tuple[jax.Array, jax.Array]]


def _spherical(z_lo: float) -> _Domain:
    # (cos theta, phi): d omega = d(cos theta) d(phi), Jacobian 1.
    def forward(p):
        return spherical_direction(p[..., 0], p[..., 1]), jnp.ones(p.shape[:-1], p.dtype)

    def backward(w):
        norm = jnp.linalg.norm(w, axis=-1)
        inside = (jnp.abs(norm - 1.0) <= 1e-3) & (w[..., 2] >= z_lo - _EPS)
        z = jnp.clip(w[..., 2] / norm, -1.0, 1.0)
        return jnp.stack([z, jnp.arctan2(w[..., 1], w[..., 0])], axis=-1), inside

    return _Domain(np.array([z_lo, -math.pi]), np.array([1.0, math.pi]), (3,), forward, backward)


def _disk() -> _Domain:
    # (r^2, phi): dA = r dr dphi = (1/2) d(r^2) dphi, so a uniform disk is uniform here.
    def forward(p):
        r = jnp.sqrt(p[..., 0])
        x = jnp.stack([r * jnp.cos(p[..., 1]), r * jnp.sin(p[..., 1])], axis=-1)
        return x, jnp.full(p.shape[:-1], 0.5, p.dtype)

    def backward(x):
        r2 = jnp.sum(x * x, axis=-1)
        inside = r2 <= 1.0 + _EPS
        return jnp.stack([r2, jnp.arctan2(x[..., 1], x[..., 0])], axis=-1), inside

    return _Domain(np.array([0.0, -math.pi]), np.array([1.0, math.pi]), (2,), forward, backward)


def _triangle() -> _Domain:
    # (s, t) in [0,1]^2 -> barycentrics (b0, b1) = (s, (1 - s) t); dA = (1 - s) ds dt.
    # The triangle's edge b0 + b1 = 1 is a grid line (t = 1), so cells never straddle it.
    def forward(p):
        s, t = p[..., 0], p[..., 1]
        return jnp.stack([s, (1.0 - s) * t], axis=-1), 1.0 - s

    def backward(b):
        b0, b1 = b[..., 0], b[..., 1]
        inside = (b0 >= -_EPS) & (b1 >= -_EPS) & (b0 + b1 <= 1.0 + _EPS)
        rest = 1.0 - b0
        t = jnp.where(rest > 0, b1 / jnp.where(rest > 0, rest, 1.0), 0.0)
        return jnp.stack([b0, t], axis=-1), inside

    return _Domain(np.array([0.0, 0.0]), np.array([1.0, 1.0]), (2,), forward, backward)


def _box(lo: np.ndarray, hi: np.ndarray) -> _Domain:
    scalar = lo.ndim == 0
    slack = _EPS * (hi - lo)

    def forward(p):
        x = p[..., 0] if scalar else p
        return x, jnp.ones(p.shape[:-1], p.dtype)

    def backward(x):
        p = x[..., None] if scalar else x
        low = jnp.broadcast_to(jnp.asarray(lo - slack, p.dtype), p.shape)
        high = jnp.broadcast_to(jnp.asarray(hi + slack, p.dtype), p.shape)
        inside = jnp.all((p >= low) & (p <= high), axis=-1)
        return p, inside

    shape = () if scalar else lo.shape
    return _Domain(np.atleast_1d(lo), np.atleast_1d(hi), shape, forward, backward)


def _domain_spec(domain: Any) -> str | tuple:
    """Validate `domain` and make it hashable: a name, or `(lo, hi)` as floats or float pairs."""
    if isinstance(domain, str):
        if domain not in _DOMAINS:
            raise ValueError(
                f"`domain` must be one of {_DOMAINS} or an interval (lo, hi), got {domain!r}."
            )
        return domain
    try:
        lo, hi = domain
        lo = np.asarray(lo, dtype=np.float64)
        hi = np.asarray(hi, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(
            f"`domain` must be one of {_DOMAINS} or a pair (lo, hi), got {domain!r}."
        ) from None
    if lo.shape != hi.shape or lo.ndim > 1 or lo.size > 2 or lo.size == 0:
        raise ValueError(
            "`domain` as (lo, hi) must be an interval (two scalars) or a rectangle (two "
            f"length-2 sequences), got lo={lo}, hi={hi}."
        )
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo < hi)):
        raise ValueError(f"`domain` (lo, hi) must be finite with lo < hi, got lo={lo}, hi={hi}.")
    if lo.ndim == 0:
        return (float(lo), float(hi))
    return (tuple(lo.tolist()), tuple(hi.tolist()))


@functools.lru_cache(maxsize=64)
def _make_domain(spec: str | tuple) -> _Domain:
    """The parameterisation of a validated domain (see `_domain_spec`)."""
    if spec == "square":
        return _box(np.zeros(2), np.ones(2))
    if spec == "disk":
        return _disk()
    if spec == "sphere":
        return _spherical(-1.0)
    if spec == "hemisphere":
        return _spherical(0.0)
    if spec == "triangle":
        return _triangle()
    lo, hi = spec
    return _box(np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64))
