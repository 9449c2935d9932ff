"""A mixture of diagonal Gaussians truncated to the box, and its EM fit to weighted samples."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .. import _random
from .._box import as_vectors
from .._checks import check_bounds, check_count, check_key
from ._base import AbstractProposal, _as_matrix, _from_matrix, split_evenly
from ._truncnorm import log_ndtr_diff, truncnorm_icdf


class GaussianMixture(AbstractProposal):
    r"""A mixture of Gaussians with diagonal covariances, truncated to the box.

    $$p(x) = \sum_{k=1}^K \pi_k \prod_{j=1}^d
    \frac{\varphi((x_j - \mu_{kj})/\sigma_{kj})}{\sigma_{kj}\,Z_{kj}},\qquad
    Z_{kj} = \Phi\Big(\frac{hi_j - \mu_{kj}}{\sigma_{kj}}\Big) -
             \Phi\Big(\frac{lo_j - \mu_{kj}}{\sigma_{kj}}\Big)$$

    with $\pi = \mathrm{softmax}(\text{logits})$ and $\sigma = e^{\text{log\_scales}}$.
    Each component is truncated on its own, so every component (and the
    mixture) integrates to one on the box exactly. Sampling picks a component
    (the weights' CDF inverted at a uniform) and inverts each axis'
    truncated-normal CDF, so `x` is a differentiable function of the means and scales
    (reparameterised); `fit` uses a stratified draw (a fixed share of samples per
    component, weighted by $\pi_k$) so the logits get exact gradients too.

    **Fields** (the parameters `fit` optimises are the unconstrained arrays):
    `logits` `(K,)`, `means` `(K, d)`, `log_scales` `(K, d)`.
    """

    lo: jax.Array
    hi: jax.Array
    logits: jax.Array
    means: jax.Array
    log_scales: jax.Array

    def __init__(self, key, lo, hi, components: int = 8, *, scale: float = 0.25):
        """**Arguments:**

        - `key`: a PRNG key for the initial means (uniform in the box).
        - `lo`, `hi`: the box (scalars or shape `(d,)`).
        - `components`: the number of Gaussians $K$ (static int >= 1).
        - `scale`: initial standard deviation as a fraction of the box width.
        """
        key = check_key(key)
        self.lo, self.hi = check_bounds(lo, hi)
        components = check_count(components, "components")
        if not (isinstance(scale, (int, float)) and scale > 0):
            raise ValueError(f"`scale` must be a positive number, got {scale!r}.")
        d = 1 if jnp.ndim(self.lo) == 0 else jnp.shape(self.lo)[0]
        lo_v = jnp.reshape(self.lo, (d,))
        hi_v = jnp.reshape(self.hi, (d,))
        dtype = self.lo.dtype
        u = jax.random.uniform(key, (components, d), dtype=dtype, minval=0.1, maxval=0.9)
        self.means = lo_v + (hi_v - lo_v) * u
        self.log_scales = jnp.broadcast_to(jnp.log(scale * (hi_v - lo_v)), (components, d))
        self.logits = jnp.zeros((components,), dtype)

    def __check_init__(self):
        k = jnp.shape(self.logits)[0] if jnp.ndim(self.logits) == 1 else None
        if (
            k is None
            or jnp.shape(self.means) != (k, self.dim)
            or jnp.shape(self.log_scales)
            != (
                k,
                self.dim,
            )
        ):
            raise ValueError(
                "GaussianMixture needs logits (K,), means (K, d) and log_scales (K, d), got "
                f"{jnp.shape(self.logits)}, {jnp.shape(self.means)}, {jnp.shape(self.log_scales)}."
            )

    @property
    def components(self) -> int:
        return jnp.shape(self.logits)[0]

    @classmethod
    def from_samples(
        cls,
        x,
        weights,
        lo,
        hi,
        components: int = 8,
        *,
        iterations: int = 50,
        min_scale: float = 0.01,
        prior: float = 1.0,
        until_noise: bool = False,
    ) -> GaussianMixture:
        r"""Fit a mixture to weighted samples by expectation-maximisation.

        With samples $x_i$ and weights $w_i \ge 0$, e.g. $w_i = |f(x_i)|/q(x_i)$ for
        $x_i \sim q$ (importance-weighted samples of $|f|$), EM maximises
        $\sum_i w_i \log p(x_i)$, i.e. minimises the forward KL divergence from
        the weighted sample distribution to $p$: responsibilities
        $r_{ik} \propto \pi_k \mathcal N(x_i; \mu_k, \sigma_k^2)$, then
        $\pi_k \propto \sum_i w_i r_{ik}$ and $\mu_k$, $\sigma_k^2$ the
        $w_i r_{ik}$-weighted mean and variance (the M-step ignores the truncation
        to the box, a good approximation for components inside it). Where the
        weights are very uneven (a few samples carry most of the mass, as in
        high dimensions), components sit on those samples; the M-step for
        $\sigma_k^2$ is therefore a MAP update that adds `prior` effective
        samples' worth of the samples' overall variance $s^2$,
        $\sigma_k^2 = (m_k v_k + \tau s^2)/(m_k + \tau)$ with $\tau =
        \text{prior}/\text{ESS}$, $\text{ESS} = 1/\sum_i w_i^2$ the effective
        sample size, $m_k = \sum_i w_i r_{ik}$ (the weights sum to one) and
        $v_k$ the weighted variance; and `min_scale` floors $\sigma$ at that
        fraction of the box width. So no component collapses to a spike, and
        well-sampled components keep their own width.

        The means start at weighted farthest points: the heaviest sample first,
        then repeatedly the sample maximising $w_i \min_k \|x_i - \mu_k\|^2$
        (a deterministic k-means++), so separated heavy clusters (the modes of
        $f$) each get a component; the scales start at the weighted standard
        deviation of all samples.

        With `until_noise`, EM stops early, once a step gains less in the weighted mean
        log-likelihood $\bar\ell = \sum_i w_i \log p(x_i)$ than its sampling error,
        $\mathrm{sd}_w(\log p)/\sqrt{\mathrm{ESS}}$: further steps fit the sample's noise,
        not $|f|$. The loop is then a `lax.while_loop`, which reverse mode cannot
        differentiate: the samples and weights are taken as constants there, and the fit
        carries no derivative.

        **Arguments:** `x` `(m, d)` (or `(m,)` for scalar bounds); `weights`
        `(m,)`; `lo`, `hi` the box; `components` $K \le m$; `iterations` EM
        steps (static; at most this many with `until_noise`); `min_scale`, `prior` as
        above.

        **Returns:** a `GaussianMixture` (a good start for `fit` or `adapt`).
        """
        lo, hi = check_bounds(lo, hi)
        components = check_count(components, "components")
        iterations = check_count(iterations, "iterations", minimum=0)
        if not (isinstance(min_scale, (int, float)) and min_scale > 0):
            raise ValueError(f"`min_scale` must be a positive number, got {min_scale!r}.")
        if not (isinstance(prior, (int, float)) and prior >= 0):
            raise ValueError(f"`prior` must be a number >= 0, got {prior!r}.")
        d = 1 if jnp.ndim(lo) == 0 else jnp.shape(lo)[0]
        x = jnp.reshape(jnp.asarray(x, lo.dtype), (-1, d))
        w = jnp.asarray(weights, lo.dtype)
        m = x.shape[0]
        if w.shape != (m,) or m < components:
            raise ValueError(
                f"`x` must have shape (m, {d}) and `weights` shape (m,) with m >= components = "
                f"{components}, got {jnp.shape(x)} and {jnp.shape(w)}."
            )
        w = jnp.where(jnp.isfinite(w) & (w > 0), w, 0.0)
        w = w / jnp.maximum(jnp.sum(w), jnp.finfo(w.dtype).tiny)
        lo_v, hi_v = jnp.reshape(lo, (d,)), jnp.reshape(hi, (d,))
        floor = min_scale * (hi_v - lo_v)

        def pick(dist, _):
            # Zero-weight samples score below every positive one (never picked while any is left).
            mean = x[jnp.argmax(jnp.where(w > 0, w * dist, -1.0))]
            return jnp.minimum(dist, jnp.sum((x - mean) ** 2, axis=-1)), mean

        first = x[jnp.argmax(w)]
        dist0 = jnp.sum((x - first) ** 2, axis=-1)
        _, rest = jax.lax.scan(pick, dist0, None, components - 1)
        means = jnp.concatenate([first[None], rest], axis=0)
        tau = prior * jnp.sum(w**2)  # prior effective samples, as a share of the mass
        centre = jnp.sum(w[:, None] * x, axis=0)
        spread = jnp.sqrt(jnp.sum(w[:, None] * (x - centre) ** 2, axis=0))
        scales = jnp.broadcast_to(jnp.maximum(spread, floor), (components, d))
        log_pi = jnp.full((components,), -jnp.log(components), x.dtype)

        # EM works on the samples about their centre (in float32, E[x^2] - mean^2 would
        # cancel when the box is far from the origin), in matrix products over (m, d) and
        # (m, K) only: no (m, K, d) array, which would take much of an EM step's time.
        xc = x - centre
        xc2 = xc * xc

        def step(log_pi, means, scales):
            mc = means - centre
            precision = scales**-2  # (K, d)
            # sum_d (x_d - mu_kd)^2 / sigma_kd^2, expanded
            quad = xc2 @ precision.T - 2 * xc @ (mc * precision).T + jnp.sum(mc**2 * precision, -1)
            log_n = -0.5 * jnp.maximum(quad, 0) - jnp.sum(jnp.log(scales), axis=-1) + log_pi
            r = jax.nn.softmax(log_n, axis=-1) * w[:, None]  # (m, K)
            mass = jnp.sum(r, axis=0)
            safe = jnp.maximum(mass, jnp.finfo(x.dtype).tiny)
            new_mc = (r.T @ xc) / safe[:, None]
            new_means = centre + new_mc
            var = jnp.maximum((r.T @ xc2) / safe[:, None] - new_mc**2, 0)
            # MAP update: `prior` effective samples of the overall spread keep components
            # that rest on one or two heavy samples from becoming spikes.
            var = (mass[:, None] * var + tau * spread**2) / (mass[:, None] + tau)
            new_scales = jnp.maximum(jnp.sqrt(var), floor)
            # A component that lost all its mass keeps its place (and a tiny weight).
            alive = mass > 0
            new_means = jnp.where(alive[:, None], new_means, means)
            new_scales = jnp.where(alive[:, None], new_scales, scales)
            new_log_pi = jnp.log(jnp.maximum(mass, 1e-12))
            new = (new_log_pi - jax.nn.logsumexp(new_log_pi), new_means, new_scales)
            return new, jax.nn.logsumexp(log_n, axis=-1)  # (and log p(x_i) before the step)

        if until_noise:
            # (What `step` reads, and where it starts.)
            w, xc, xc2, centre, spread, tau, start = jax.lax.stop_gradient(
                (w, xc, xc2, centre, spread, tau, (log_pi, means, scales)))
            ess = 1 / jnp.maximum(jnp.sum(w**2), jnp.finfo(w.dtype).tiny)

            def go_on(carry):
                _, count, _, gain, noise = carry
                return (count < iterations) & ((count < 2) | (gain >= noise))

            def em_until(carry):
                params, count, before, _, _ = carry
                new, log_p = step(*params)
                now = jnp.sum(w * log_p)  # the mean log-likelihood of `params`
                noise = jnp.sqrt(jnp.sum(w * (log_p - now) ** 2) / ess)
                return new, count + 1, now, now - before, noise

            zero = jnp.zeros((), x.dtype)
            (log_pi, means, scales), _, _, _, _ = jax.lax.while_loop(
                go_on, em_until, (start, 0, zero, zero, zero))
        else:
            (log_pi, means, scales), _ = jax.lax.scan(
                lambda params, _: (step(*params)[0], None), (log_pi, means, scales), None,
                iterations)
        gm = cls(jax.random.key(0), lo, hi, components)
        return eqx.tree_at(
            lambda g: (g.logits, g.means, g.log_scales),
            gm,
            (log_pi, jnp.clip(means, lo_v, hi_v), jnp.log(scales)),
        )

    def _component_log_pdf(self, x: jax.Array) -> jax.Array:
        r"""`(m, d) -> (m, K)`: each truncated component's log density,
        $-\frac12 \sum_j z_{kj}^2 - \sum_j (\log\sigma_{kj} + \log Z_{kj}) - \frac d2 \log 2\pi$
        with $z_{kj} = (x_j - \mu_{kj})/\sigma_{kj}$ and $Z_{kj}$ the mass of the box."""
        lo, hi = as_vectors(self.lo, self.hi)
        sigma = jnp.exp(self.log_scales)
        log_z = log_ndtr_diff((lo - self.means) / sigma, (hi - self.means) / sigma)
        const = -jnp.sum(self.log_scales + log_z, axis=-1) - 0.5 * x.shape[-1] * jnp.log(2 * jnp.pi)
        if jnp.finfo(x.dtype).bits >= 64:
            # sum_j z^2 = x^2 . w - 2 x . (w mu) + mu^2 . w with w = sigma^-2: matrix products
            # instead of (m, K, d) arrays (faster on a CPU).
            # About the box's centre, the cancellation costs ~1e-16 (width/sigma)^2: nothing
            # in float64, too much in float32 for the narrow components EM can fit.
            centre = (lo + hi) / 2
            xc, mc = x - centre, self.means - centre
            w = jnp.exp(-2 * self.log_scales)
            dot = lambda a, b: jnp.matmul(a, b.T, precision=jax.lax.Precision.HIGHEST)
            quad = dot(xc**2, w) - 2 * dot(xc, w * mc) + jnp.sum(w * mc**2, axis=-1)
        else:
            quad = jnp.sum(((x[:, None, :] - self.means) / sigma) ** 2, axis=-1)
        return const - 0.5 * quad

    def log_pdf(self, x):
        xm, batch = _as_matrix(self, x)
        log_w = jax.nn.log_softmax(self.logits)
        lp = jax.nn.logsumexp(self._component_log_pdf(xm) + log_w, axis=-1)
        lo, hi = as_vectors(self.lo, self.hi)
        inside = jnp.all((xm >= lo) & (xm <= hi), axis=-1)
        return jnp.reshape(jnp.where(inside, lp, -jnp.inf), batch)

    def _sample_component(self, u: jax.Array, k: jax.Array) -> jax.Array:
        lo, hi = as_vectors(self.lo, self.hi)
        return truncnorm_icdf(u, self.means, jnp.exp(self.log_scales), lo, hi, component=k)

    def sample(self, key, n):
        key = check_key(key)
        n = check_count(n)
        key_c, key_u = jax.random.split(key)
        k = _random.categorical(key_c, self.logits, n)
        u = _random.uniform(key_u, (n, self.dim), self.lo.dtype)
        x = _from_matrix(self, self._sample_component(u, k))
        return x, self.pdf(x)

    def weighted_draw(self, key, n):
        """Stratified over components: `n_k` samples from component k, weight `pi_k / n_k`."""
        counts = split_evenly(n, self.components)
        k = jnp.concatenate([jnp.full((c,), i, dtype=jnp.int32) for i, c in enumerate(counts)])
        u = _random.uniform(key, (n, self.dim), self.lo.dtype)
        x = _from_matrix(self, self._sample_component(u, k))
        pi = jax.nn.softmax(self.logits)
        w = pi[k] / jnp.asarray(counts, dtype=pi.dtype)[k]
        return x, self.log_pdf(x), w

