"""A finite mixture of proposals on the same box (e.g. defensive importance sampling)."""

from __future__ import annotations

import math

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

    With `stratified=True` (fixed, concrete weights), `sample(key, n)` draws
    $n_k$ points from component $k$, the $n w_k$ rounded to whole points that
    sum to $n$ (largest remainders), and returns each point's density under
    the mixture of those shares, $\sum_k (n_k/n)\,p_k(x)$: the deterministic
    mixture of multiple importance sampling (Veach and Guibas 1995; Owen and
    Zhou 2000). $\frac1n\sum_i f(x_i)/p(x_i)$ stays unbiased, its variance is
    never above that of i.i.d. component choice (the i.i.d. variance of the
    values is then a conservative error bar), and no component is drawn for
    points it does not serve (i.i.d. choice, vectorised, draws every point from
    every component). The
    components' points come evenly interleaved and turned by a uniform random
    offset, so that each place holds component $k$ with probability $n_k/n$ and
    any first $m$ of them hold $m n_k/n$ give or take one: their mean is
    unbiased too, and the make-up of such a prefix adds no variance of its own.
    """

    proposals: tuple
    log_weights: jax.Array
    train_weights: bool = eqx.field(static=True)
    shares: tuple[float, ...] | None = eqx.field(static=True)

    def __init__(self, proposals, weights=None, *, train_weights: bool = False,
                 stratified: bool = False):
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
            weights = np.full(k, 1.0 / k)
        # (Numbers given stay concrete here even under jit, where jnp makes tracers of them.)
        given = weights
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
        self.shares = None
        if stratified:
            if train_weights or not all(is_concrete(w) for w in jax.tree.leaves(given)):
                raise ValueError(
                    "`stratified=True` needs fixed, concrete `weights` (the points per "
                    "component are static): pass numbers, and train_weights=False."
                )
            wn = np.asarray(given, np.float64)
            self.shares = tuple(float(w) for w in wn / wn.sum())

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

    def counts(self, n: int) -> tuple[int, ...]:
        """Points per component of a stratified `sample` of `n`: $n w_k$ rounded by largest
        remainders (static)."""
        if self.shares is None:
            raise ValueError("`counts` is for a Mixture made with stratified=True.")
        exact = np.asarray(self.shares) * n
        counts = np.floor(exact).astype(int)
        counts[np.argsort(-(exact - counts), kind="stable")[: n - counts.sum()]] += 1
        return tuple(int(c) for c in counts)

    def sample(self, key, n):
        key = check_key(key)
        n = check_count(n)
        if self.shares is not None:
            return self._stratified_sample(key, n)
        keys = jax.random.split(key, len(self.proposals) + 1)
        k = _random.categorical(keys[0], self.log_weights, n)
        xs = [p.sample(kk, n)[0] for p, kk in zip(self.proposals, keys[1:])]
        x = xs[0]
        for i, xi in enumerate(xs[1:], start=1):
            sel = k == i if self.event_ndim == 0 else (k == i)[:, None]
            x = jnp.where(sel, xi, x)
        return x, self.pdf(x)

    def _stratified_sample(self, key, n):
        """`counts(n)[k]` points from component `k`, with their density under the mixture of
        the realised shares (see the class docstring), rotated by a random offset."""
        counts = self.counts(n)
        keys = jax.random.split(key, len(self.proposals) + 1)
        parts = [p.sample(k, c)[0] for p, k, c in zip(self.proposals, keys[1:], counts) if c > 0]
        # The components' points interleaved evenly (each at the centres of its own n_k
        # slots of [0, 1)), so that any run of m places holds m n_k / n of them, give or
        # take one: a stream's last block keeps only its first points.
        slots = np.concatenate([(np.arange(c) + 0.5) / c for c in counts if c > 0])
        x = jnp.concatenate(parts, axis=0)[np.argsort(slots, kind="stable")]
        lps = [p.log_pdf(x) + math.log(c / n) for p, c in zip(self.proposals, counts) if c > 0]
        p = jnp.exp(jax.nn.logsumexp(jnp.stack(lps, axis=-1), axis=-1))
        # A uniform rotation makes each place's component k with probability n_k / n: the
        # mean of any first m points is unbiased too.
        shift = jax.random.randint(keys[0], (), 0, n)
        return jnp.roll(x, shift, axis=0), jnp.roll(p, shift)

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
