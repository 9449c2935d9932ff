"""A finite mixture of proposals on the same box (e.g. defensive importance sampling)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _random
from .._checks import check_count, check_key, is_concrete
from ._base import AbstractProposal, check_proposal, split_evenly


class Mixture(AbstractProposal):
    r"""A finite mixture $p(x) = \sum_k w_k p_k(x)$ of proposals on the same box.

    E.g. a fitted density mixed with `Uniform` at weight $\alpha$ (defensive
    importance sampling, Hesterberg 1995), so no region is starved:
    `Mixture((fitted, Uniform(lo, hi)), (0.9, 0.1))`. `sample` picks each
    sample's component at random (i.i.d. from the mixture). The weights are
    fixed unless `train_weights=True` (then `fit` optimises their logits).
    """

    proposals: tuple
    log_weights: jax.Array
    train_weights: bool = eqx.field(static=True)

    def __init__(self, proposals, weights=None, *, train_weights: bool = False):
        proposals = tuple(proposals)
        if not proposals:
            raise ValueError("`proposals` must be a non-empty sequence of proposals.")
        for i, p in enumerate(proposals):
            check_proposal(p, f"proposals[{i}]", ("sample", "log_pdf"))
            if jnp.shape(p.lo) != jnp.shape(proposals[0].lo):
                raise ValueError(
                    f"`proposals` must share the bounds' shape, got {jnp.shape(p.lo)} and "
                    f"{jnp.shape(proposals[0].lo)}."
                )
        k = len(proposals)
        if weights is None:
            weights = jnp.full((k,), 1.0 / k, jnp.result_type(proposals[0].lo))
        weights = jnp.asarray(weights, jnp.result_type(proposals[0].lo))
        if weights.shape != (k,):
            raise ValueError(f"`weights` must have shape ({k},), got {weights.shape}.")
        if is_concrete(weights):
            wn = np.asarray(weights)
            if not (np.all(np.isfinite(wn)) and np.all(wn >= 0) and wn.sum() > 0):
                raise ValueError(f"`weights` must be non-negative and not all zero, got {wn}.")
        self.proposals = proposals
        self.log_weights = jnp.log(weights / jnp.sum(weights))
        self.train_weights = bool(train_weights)

    @property
    def lo(self):
        return self.proposals[0].lo

    @property
    def hi(self):
        return self.proposals[0].hi

    def _log_w(self):
        lw = jax.nn.log_softmax(self.log_weights)
        return lw if self.train_weights else jax.lax.stop_gradient(lw)

    def log_pdf(self, x):
        self._batch_shape(x)
        lps = jnp.stack([p.log_pdf(x) for p in self.proposals], axis=-1)
        return jax.nn.logsumexp(lps + self._log_w(), axis=-1)

    def sample(self, key, n):
        key = check_key(key)
        n = check_count(n)
        keys = jax.random.split(key, len(self.proposals) + 1)
        k = _random.categorical(keys[0], self.log_weights, n)
        xs = [p.sample(kk, n)[0] for p, kk in zip(self.proposals, keys[1:])]
        x = xs[0]
        for i, xi in enumerate(xs[1:], start=1):
            sel = k == i if self.event_ndim == 0 else (k == i)[:, None]
            x = jnp.where(sel, xi, x)
        return x, self.pdf(x)

    def weighted_draw(self, key, n):
        """Stratified over components with weights `w_k / n_k` (exact gradients in `w`)."""
        counts = split_evenly(n, len(self.proposals))
        if min(counts) < 1:
            raise ValueError(f"`n` must be at least the number of components, got {n}.")
        keys = jax.random.split(key, len(self.proposals))
        xs = [p.sample(kk, c)[0] for p, kk, c in zip(self.proposals, keys, counts)]
        x = jnp.concatenate(xs, axis=0)
        idx = jnp.concatenate([jnp.full((c,), i) for i, c in enumerate(counts)])
        w = jnp.exp(self._log_w())[idx] / jnp.asarray(counts, self.log_weights.dtype)[idx]
        return x, self.log_pdf(x), w
