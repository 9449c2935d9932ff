r"""Parametric, differentiable importance densities on a box $[lo, hi]$.

A *proposal* is any object with `sample(key, n) -> (x, pdf)` and `pdf(x)` (and
`log_pdf(x)`). `x` has shape `(n, d)` for `(d,)` bounds, or `(n,)` for scalar
bounds; `pdf` takes a batch `(n, d) -> (n,)` or one point `(d,) -> ()`.
jaxmc's proposals are equinox Modules (pytrees), so they pass through `jit`
and their array fields are the parameters `fit` optimises.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp

from ._checks import check_bounds, check_count, check_key


class AbstractProposal(eqx.Module):
    """Base class of jaxmc's proposals on a box `[lo, hi]`.

    Subclasses implement `_sample_unit(key, n) -> (u, log_pdf_unit)` *or*
    override `sample`, and `log_pdf`. `event_ndim` is 0 for scalar bounds and 1
    for `(d,)` bounds; it decides whether `pdf(x)` sees one point or a batch.
    """

    lo: eqx.AbstractVar[jax.Array]
    hi: eqx.AbstractVar[jax.Array]

    @property
    def event_ndim(self) -> int:
        return jnp.ndim(self.lo)

    @property
    def dim(self) -> int:
        return 1 if jnp.ndim(self.lo) == 0 else jnp.shape(self.lo)[0]

    @abc.abstractmethod
    def sample(self, key: jax.Array, n: int) -> tuple[jax.Array, jax.Array]:
        """Draw `n` points; returns `(x, pdf(x))`."""

    @abc.abstractmethod
    def log_pdf(self, x: jax.Array) -> jax.Array:
        """Log density w.r.t. Lebesgue measure; one point or a batch."""

    def pdf(self, x: jax.Array) -> jax.Array:
        """Density w.r.t. Lebesgue measure; one point `(d,) -> ()` or a batch `(n, d) -> (n,)`."""
        return jnp.exp(self.log_pdf(x))

    def _batch_shape(self, x: jax.Array) -> tuple[int, ...]:
        x = jnp.asarray(x)
        if x.ndim < self.event_ndim or x.shape[x.ndim - self.event_ndim :] != jnp.shape(self.lo):
            raise ValueError(
                f"`x` must have shape (..., {', '.join(map(str, jnp.shape(self.lo)))}) "
                f"to match the proposal's bounds, got {x.shape}."
            )
        return x.shape[: x.ndim - self.event_ndim]

    def _inside(self, x: jax.Array) -> jax.Array:
        inside = (x >= self.lo) & (x <= self.hi)
        return inside if self.event_ndim == 0 else jnp.all(inside, axis=-1)


class Uniform(AbstractProposal):
    r"""The uniform density $1/\prod_j (hi_j - lo_j)$ on the box `[lo, hi]`."""

    lo: jax.Array
    hi: jax.Array

    def __init__(self, lo, hi):
        self.lo, self.hi = check_bounds(lo, hi)

    def sample(self, key, n):
        key = check_key(key)
        n = check_count(n)
        shape = (n,) + jnp.shape(self.lo)
        u = jax.random.uniform(key, shape, dtype=jnp.result_type(self.lo))
        x = self.lo + (self.hi - self.lo) * u
        pdf = jnp.broadcast_to(jnp.exp(-self._log_volume()), (n,))
        return x, pdf

    def _log_volume(self) -> jax.Array:
        return jnp.sum(jnp.log(self.hi - self.lo))

    def log_pdf(self, x):
        batch = self._batch_shape(x)
        inside = self._inside(jnp.asarray(x))
        return jnp.broadcast_to(jnp.where(inside, -self._log_volume(), -jnp.inf), batch)
