r"""The proposal contract: `AbstractProposal`, maps from the unit cube, the weighted draw.

A *proposal* is a density $p$ on a box $[lo, hi]$ that can be sampled. Every
consumer (the estimators, `fit`, `adapt`, `integrate`) uses only the public
methods of `AbstractProposal`: `sample`, `log_pdf`, `pdf` and `weighted_draw`,
the reparameterised draw that fitting differentiates through. Densities that
are a map $T$ of the unit cube with a tractable Jacobian ($x = T(u)$,
$p(x) = 1/|\det \partial T(u)|$: `Grid`, `PiecewiseLinear`, `Flow`) share
`AbstractUnitMap`, which samples by mapping uniform points.
"""

from __future__ import annotations

import abc
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from .. import _random
from .._checks import check_count, check_key


class AbstractProposal(eqx.Module):
    """Base class of jaxmc's proposals on a box `[lo, hi]`.

    Subclasses implement `sample` and `log_pdf`, and override `weighted_draw`
    where a better reparameterised draw exists (e.g. stratified over mixture
    components). `event_ndim` is 0 for scalar bounds and 1 for `(d,)` bounds; it
    decides whether `pdf(x)` sees one point or a batch.
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

    def weighted_draw(self, key: jax.Array, n: int) -> tuple[jax.Array, jax.Array, jax.Array]:
        r"""A reparameterised draw for fitting: `(x, log_pdf(x), weights)`.

        `sum(weights * g(x))` estimates $E_p[g]$ and is a differentiable
        function of the parameters for a fixed `key`. The default is `sample`
        with equal weights $1/n$; mixtures override it with a stratified draw
        whose weights carry the mixture weights (so those get exact gradients).
        """
        x, pdf = self.sample(key, n)
        log_p = jnp.log(pdf)
        return x, log_p, jnp.full((n,), 1.0 / n, log_p.dtype)

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


class AbstractUnitMap(AbstractProposal):
    r"""A proposal that is a map of the unit cube: $x = T(u)$, $u \sim U(0,1)^d$.

    Subclasses define `map(u) -> (x, log_pdf(x))` on a batch `u` of shape
    `(m, d)`; $\log p(x) = -\log|\det \partial T(u)|$ comes out of the same
    pass, so sampling never inverts the map.
    """

    @abc.abstractmethod
    def map(self, u: jax.Array) -> tuple[jax.Array, jax.Array]:
        """`u` `(m, d)` in $(0,1)^d$ to `x` `(m, d)` in the open box and `log_pdf(x)` `(m,)`."""

    def sample(self, key, n):
        key = check_key(key)
        n = check_count(n)
        u = _random.uniform(key, (n, self.dim), self.lo.dtype)
        x, log_p = self.map(u)
        return _from_matrix(self, x), jnp.exp(log_p)

    def weighted_draw(self, key, n):
        # The map's log density directly: exp then log would underflow in high dimensions.
        u = _random.uniform(key, (n, self.dim), self.lo.dtype)
        x, log_p = self.map(u)
        return _from_matrix(self, x), log_p, jnp.full((n,), 1.0 / n, log_p.dtype)


def weighted_draw(proposal: Any, key: jax.Array, n: int):
    """`proposal.weighted_draw(key, n)`, or `sample` with equal weights for any other sampler."""
    if isinstance(proposal, AbstractProposal):
        return proposal.weighted_draw(key, n)
    x, pdf = proposal.sample(key, n)
    log_p = jnp.log(pdf)
    return x, log_p, jnp.full((n,), 1.0 / n, log_p.dtype)


_SIGNATURES = {"sample": "sample(key, n) -> (x, pdf)", "pdf": "pdf(x)", "log_pdf": "log_pdf(x)"}


def check_proposal(
    proposal: Any, name: str = "proposal", methods: tuple[str, ...] = ("sample", "pdf")
) -> Any:
    """Check that `proposal` has the `methods` a consumer calls (the estimators need
    `sample` and `pdf`; fitting needs `sample` and `log_pdf`)."""
    if not all(callable(getattr(proposal, m, None)) for m in methods):
        wanted = " and ".join(_SIGNATURES[m] for m in methods)
        raise TypeError(f"`{name}` must have methods {wanted}, got {type(proposal).__name__}.")
    return proposal


def _as_matrix(proposal: AbstractProposal, x: jax.Array) -> tuple[jax.Array, tuple[int, ...]]:
    """`x` as `(m, d)` plus the batch shape to restore (scalar bounds are `d = 1`)."""
    x = jnp.asarray(x)
    batch = proposal._batch_shape(x)
    return jnp.reshape(x, (-1, proposal.dim)), batch


def _from_matrix(proposal: AbstractProposal, x: jax.Array) -> jax.Array:
    """`(n, d)` back to `(n,)` for scalar bounds."""
    return x[:, 0] if proposal.event_ndim == 0 else x


def sum_last(a: jax.Array) -> jax.Array:
    """Sum over a short last axis as explicit adds (XLA on the CPU reduces a trailing
    axis of a few elements more slowly than it adds columns)."""
    if a.shape[-1] > 16:
        return jnp.sum(a, axis=-1)
    total = a[..., 0]
    for j in range(1, a.shape[-1]):
        total = total + a[..., j]
    return total


def split_evenly(n: int, k: int) -> tuple[int, ...]:
    """Split `n` samples over `k` components as evenly as possible (static sizes)."""
    base, extra = divmod(n, k)
    return tuple(base + (i < extra) for i in range(k))
