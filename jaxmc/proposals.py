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
import numpy as np
from jax.scipy.special import log_ndtr, ndtr, ndtri

from . import _random
from ._checks import check_bounds, check_count, check_key, is_concrete


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

    def _draw(self, key: jax.Array, n: int) -> tuple[jax.Array, jax.Array, jax.Array]:
        """A reparameterised draw for fitting: `(x, log_pdf(x), weights)`.

        `sum(weights * g(x))` estimates $E_p[g]$ and is a differentiable
        function of the parameters for a fixed `key`. The default is `sample`
        with equal weights $1/n$; mixtures override it with a stratified draw
        whose weights carry the mixture weights (so those get exact gradients).
        """
        x, pdf = self.sample(key, n)
        log_p = jnp.log(pdf)
        return x, log_p, jnp.full((n,), 1.0 / n, log_p.dtype)


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
        u = _random.uniform(key, shape, jnp.result_type(self.lo))
        x = self.lo + (self.hi - self.lo) * u
        pdf = jnp.broadcast_to(jnp.exp(-self._log_volume()), (n,))
        return x, pdf

    def _log_volume(self) -> jax.Array:
        return jnp.sum(jnp.log(self.hi - self.lo))

    def log_pdf(self, x):
        batch = self._batch_shape(x)
        inside = self._inside(jnp.asarray(x))
        return jnp.broadcast_to(jnp.where(inside, -self._log_volume(), -jnp.inf), batch)


# ---------------------------------------------------------------------------
# Helpers shared by the fitted proposals.


def _as_matrix(proposal: AbstractProposal, x: jax.Array) -> tuple[jax.Array, tuple[int, ...]]:
    """`x` as `(m, d)` plus the batch shape to restore (scalar bounds are `d = 1`)."""
    x = jnp.asarray(x)
    batch = proposal._batch_shape(x)
    return jnp.reshape(x, (-1, proposal.dim)), batch


def _from_matrix(proposal: AbstractProposal, x: jax.Array) -> jax.Array:
    """`(n, d)` back to `(n,)` for scalar bounds."""
    return x[:, 0] if proposal.event_ndim == 0 else x


def _sum_last(a: jax.Array) -> jax.Array:
    """Sum over a short last axis as explicit adds (XLA on the CPU reduces a trailing
    axis of a few elements several times slower than it adds columns)."""
    if a.shape[-1] > 16:
        return jnp.sum(a, axis=-1)
    total = a[..., 0]
    for j in range(1, a.shape[-1]):
        total = total + a[..., j]
    return total


def _allocate(n: int, k: int) -> tuple[int, ...]:
    """Split `n` samples over `k` components as evenly as possible (static sizes)."""
    base, extra = divmod(n, k)
    return tuple(base + (i < extra) for i in range(k))


def _log_ndtr_diff(a: jax.Array, b: jax.Array) -> jax.Array:
    r"""$\log(\Phi(b) - \Phi(a))$ for $a < b$, accurate in both tails.

    Reflects to the lower tail ($\Phi(b) - \Phi(a) = \Phi(-a) - \Phi(-b)$) where
    that keeps the difference of two small numbers, and subtracts in log space.
    """
    flip = a > 0
    lo = jnp.where(flip, -b, a)
    hi = jnp.where(flip, -a, b)
    log_hi = log_ndtr(hi)
    log_lo = log_ndtr(lo)
    # log(exp(log_hi) - exp(log_lo)) = log_hi + log1p(-exp(log_lo - log_hi)).
    return log_hi + jnp.log1p(-jnp.exp(jnp.minimum(log_lo - log_hi, -1e-300)))


def _truncnorm_icdf(u: jax.Array, mu: jax.Array, sigma: jax.Array, lo, hi) -> jax.Array:
    r"""Inverse CDF of $\mathcal N(\mu, \sigma^2)$ truncated to $[lo, hi]$ at `u`.

    $x = \mu + \sigma\,\Phi^{-1}(\Phi(a) + u(\Phi(b) - \Phi(a)))$ with
    $a = (lo-\mu)/\sigma$, $b = (hi-\mu)/\sigma$, computed on the side of the
    mean where the CDF values are not close to 1 (so both tails keep their
    precision). Differentiable in $\mu$, $\sigma$: the reparameterised sample.
    """
    a = (lo - mu) / sigma
    b = (hi - mu) / sigma
    flip = (a + b) > 0  # box mostly above the mean: work with the reflected variable
    a2 = jnp.where(flip, -b, a)
    b2 = jnp.where(flip, -a, b)
    u2 = jnp.where(flip, 1 - u, u)
    pa = ndtr(a2)
    pb = ndtr(b2)
    eps = jnp.finfo(jnp.result_type(u)).tiny
    z = ndtri(jnp.clip(pa + u2 * (pb - pa), eps, 1 - jnp.finfo(jnp.result_type(u)).epsneg))
    # Far in the lower tail Phi underflows; there the truncated normal is an
    # exponential with rate |b| below b (Mills ratio), inverted in closed form.
    lam = jnp.maximum(-b2, 1.0)
    e_t = jnp.exp(-lam * (b2 - a2))
    t = -jnp.log(u2 * (1 - e_t) + e_t) / lam
    z = jnp.where(b2 < -30.0, b2 - t, z)
    z = jnp.clip(z, a2, b2)
    z = jnp.where(flip, -z, z)
    return jnp.clip(mu + sigma * z, lo, hi)


class GaussianMixture(AbstractProposal):
    r"""A mixture of Gaussians with diagonal covariances, truncated to the box.

    $$p(x) = \sum_{k=1}^K \pi_k \prod_{j=1}^d
    \frac{\varphi((x_j - \mu_{kj})/\sigma_{kj})}{\sigma_{kj}\,Z_{kj}},\qquad
    Z_{kj} = \Phi\Big(\frac{hi_j - \mu_{kj}}{\sigma_{kj}}\Big) -
             \Phi\Big(\frac{lo_j - \mu_{kj}}{\sigma_{kj}}\Big)$$

    with $\pi = \mathrm{softmax}(\text{logits})$ and $\sigma = e^{\text{log\_scales}}$.
    Each component is truncated on its own, so every component (and the
    mixture) integrates to one on the box exactly. Sampling picks a component
    with `jax.random.categorical` and inverts each axis' truncated-normal CDF,
    so `x` is a differentiable function of the means and scales
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

        **Arguments:** `x` `(m, d)` (or `(m,)` for scalar bounds); `weights`
        `(m,)`; `lo`, `hi` the box; `components` $K \le m$; `iterations` EM
        steps (static); `min_scale`, `prior` as above.

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

        def em(carry, _):
            log_pi, means, scales = carry
            z = (x[:, None, :] - means) / scales
            log_n = jnp.sum(-0.5 * z**2 - jnp.log(scales), axis=-1) + log_pi
            r = jax.nn.softmax(log_n, axis=-1) * w[:, None]  # (m, K)
            mass = jnp.sum(r, axis=0)
            safe = jnp.maximum(mass, jnp.finfo(x.dtype).tiny)
            new_means = (r.T @ x) / safe[:, None]
            # Two passes (deviations from the new means): E[x^2] - mean^2 cancels in float32
            # when the box is far from the origin.
            dev2 = (x[:, None, :] - new_means) ** 2
            var = jnp.einsum("mk,mkd->kd", r, dev2) / safe[:, None]
            # MAP update: `prior` effective samples of the overall spread keep components
            # that rest on one or two heavy samples from becoming spikes.
            var = (mass[:, None] * var + tau * spread**2) / (mass[:, None] + tau)
            new_scales = jnp.maximum(jnp.sqrt(var), floor)
            # A component that lost all its mass keeps its place (and a tiny weight).
            alive = mass > 0
            new_means = jnp.where(alive[:, None], new_means, means)
            new_scales = jnp.where(alive[:, None], new_scales, scales)
            new_log_pi = jnp.log(jnp.maximum(mass, 1e-12))
            return (new_log_pi - jax.nn.logsumexp(new_log_pi), new_means, new_scales), None

        (log_pi, means, scales), _ = jax.lax.scan(em, (log_pi, means, scales), None, iterations)
        gm = cls(jax.random.key(0), lo, hi, components)
        return eqx.tree_at(
            lambda g: (g.logits, g.means, g.log_scales),
            gm,
            (log_pi, jnp.clip(means, lo_v, hi_v), jnp.log(scales)),
        )

    def _box(self):
        d = self.dim
        return jnp.reshape(self.lo, (d,)), jnp.reshape(self.hi, (d,))

    def _component_log_pdf(self, x: jax.Array) -> jax.Array:
        """`(m, d) -> (m, K)`: each truncated component's log density."""
        lo, hi = self._box()
        sigma = jnp.exp(self.log_scales)
        z = (x[:, None, :] - self.means) / sigma
        log_z = _log_ndtr_diff((lo - self.means) / sigma, (hi - self.means) / sigma)
        log_phi = -0.5 * z**2 - 0.5 * jnp.log(2 * jnp.pi)
        return jnp.sum(log_phi - self.log_scales - log_z, axis=-1)

    def log_pdf(self, x):
        xm, batch = _as_matrix(self, x)
        log_w = jax.nn.log_softmax(self.logits)
        lp = jax.nn.logsumexp(self._component_log_pdf(xm) + log_w, axis=-1)
        inside = jnp.all((xm >= self._box()[0]) & (xm <= self._box()[1]), axis=-1)
        return jnp.reshape(jnp.where(inside, lp, -jnp.inf), batch)

    def _sample_component(self, u: jax.Array, k: jax.Array) -> jax.Array:
        lo, hi = self._box()
        return _truncnorm_icdf(u, self.means[k], jnp.exp(self.log_scales[k]), lo, hi)

    def sample(self, key, n):
        key = check_key(key)
        n = check_count(n)
        key_c, key_u = jax.random.split(key)
        k = jax.random.categorical(key_c, self.logits, shape=(n,))
        u = _random.uniform(key_u, (n, self.dim), self.lo.dtype)
        x = _from_matrix(self, self._sample_component(u, k))
        return x, self.pdf(x)

    def _draw(self, key, n):
        """Stratified over components: `n_k` samples from component k, weight `pi_k / n_k`."""
        counts = _allocate(n, self.components)
        k = jnp.concatenate([jnp.full((c,), i, dtype=jnp.int32) for i, c in enumerate(counts)])
        u = _random.uniform(key, (n, self.dim), self.lo.dtype)
        x = _from_matrix(self, self._sample_component(u, k))
        pi = jax.nn.softmax(self.logits)
        w = pi[k] / jnp.asarray(counts, dtype=pi.dtype)[k]
        return x, self.log_pdf(x), w


class _MappedProposal(AbstractProposal):
    """A proposal sampled by mapping uniform points: subclasses define `map(u) -> (x, log_pdf)`."""

    @abc.abstractmethod
    def map(self, u: jax.Array) -> tuple[jax.Array, jax.Array]:
        """`u` `(m, d)` in $[0,1)^d$ to `x` `(m, d)` and `log_pdf(x)`."""

    def sample(self, key, n):
        key = check_key(key)
        n = check_count(n)
        u = _random.uniform(key, (n, self.dim), self.lo.dtype)
        x, log_p = self.map(u)
        return _from_matrix(self, x), jnp.exp(log_p)

    def _draw(self, key, n):
        # The map's log density directly: exp then log would underflow in high dimensions.
        u = _random.uniform(key, (n, self.dim), self.lo.dtype)
        x, log_p = self.map(u)
        return _from_matrix(self, x), log_p, jnp.full((n,), 1.0 / n, log_p.dtype)


def _grid_check(bins: int) -> int:
    return check_count(bins, "bins", minimum=1)


class Grid(_MappedProposal):
    r"""VEGAS's separable piecewise-constant density (Lepage 1978, 2021).

    Each axis $j$ has `bins` bins with edges $lo_j = e_{j0} < \dots < e_{jN} = hi_j$;
    every bin carries probability $1/N$, so the density is
    $$p(x) = \prod_j \frac{1}{N\,\Delta_{j,i_j(x)}}$$
    where $\Delta_{ji}$ is the width of the bin of $x_j$. Sampling maps
    $u \in [0,1)^d$ through the piecewise-linear map $x_j = e_{ji} + \Delta_{ji}(Nu_j - i)$,
    $i = \lfloor N u_j\rfloor$, so $x$ is differentiable in the widths. The widths
    are the softmax of unconstrained `logits` `(d, N)` (in units of the box width),
    so `fit` can optimise them; `refine` applies the classic VEGAS rule instead.

    The VEGAS rule (`refine`, or `jaxmc.fit.adapt`) is the reliable way to
    adapt a grid. A gradient fit works with a first-order optimiser on fresh
    samples (`fit(..., solver=OptaxMinimiser(adam), resample=True)`), but
    BFGS on fixed samples tends to stall: the density at a fixed point jumps
    when an edge crosses it, so the sample-average objective is only
    piecewise smooth in the edges.
    """

    lo: jax.Array
    hi: jax.Array
    logits: jax.Array

    def __init__(self, lo, hi, bins: int = 64, *, edges=None):
        """**Arguments:**

        - `lo`, `hi`: the box (scalars or shape `(d,)`).
        - `bins`: the number of bins per axis $N$ (static int).
        - `edges`: optional initial edges `(d, N + 1)` (or `(N + 1,)` for scalar
          bounds), strictly increasing from `lo` to `hi`; default uniform.
        """
        self.lo, self.hi = check_bounds(lo, hi)
        bins = _grid_check(bins)
        d = 1 if jnp.ndim(self.lo) == 0 else jnp.shape(self.lo)[0]
        if edges is None:
            self.logits = jnp.zeros((d, bins), self.lo.dtype)
        else:
            edges = jnp.reshape(jnp.asarray(edges, self.lo.dtype), (d, -1))
            if edges.shape != (d, bins + 1):
                raise ValueError(f"`edges` must have shape ({d}, {bins + 1}), got {edges.shape}.")
            widths = jnp.diff(edges, axis=-1)
            if is_concrete(widths) and not bool(jnp.all(widths > 0)):
                raise ValueError("`edges` must be strictly increasing along each axis.")
            self.logits = jnp.log(widths / jnp.sum(widths, axis=-1, keepdims=True))

    def __check_init__(self):
        if jnp.ndim(self.logits) != 2 or jnp.shape(self.logits)[0] != self.dim:
            raise ValueError(
                f"Grid needs logits of shape (d, bins) = ({self.dim}, N), got {jnp.shape(self.logits)}."
            )

    @property
    def bins(self) -> int:
        return jnp.shape(self.logits)[1]

    def _unit_edges(self) -> tuple[jax.Array, jax.Array]:
        """Widths `(d, N)` and edges `(d, N+1)` in unit coordinates."""
        w = jax.nn.softmax(self.logits, axis=-1)
        e = jnp.concatenate([jnp.zeros_like(w[:, :1]), jnp.cumsum(w, axis=-1)], axis=-1)
        e = e / e[:, -1:]
        return w, e

    @property
    def edges(self) -> jax.Array:
        """Bin edges in the box's coordinates, `(d, N + 1)`."""
        _, e = self._unit_edges()
        lo = jnp.reshape(self.lo, (self.dim, 1))
        hi = jnp.reshape(self.hi, (self.dim, 1))
        return lo + (hi - lo) * e

    def _log_volume(self):
        return jnp.sum(jnp.log(self.hi - self.lo))

    def map(self, u: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The VEGAS map: `u` `(m, d)` in $[0,1)^d$ to `x` `(m, d)` and `log_pdf(x)`."""
        x, log_p, _ = self._map(u)
        return x, log_p

    def _table(self) -> tuple[jax.Array, jax.Array, jax.Array]:
        r"""Per (axis, bin), flattened to `(d * N,)`: left edge, width, and $\log(N\,\text{width})$."""
        w, e = self._unit_edges()
        log_w = jax.nn.log_softmax(self.logits, axis=-1) + jnp.log(self.bins)
        return tuple(jnp.reshape(t, (-1,)) for t in (e[:, :-1], w, log_w))

    def _map(self, u: jax.Array, table=None) -> tuple[jax.Array, jax.Array, jax.Array]:
        """`map` plus each point's per-axis bin index `(m, d)`, which `refine` needs.

        `table` is `_table()`, passed in by loops that keep it stored: XLA on the
        CPU fuses the table's softmax and logs into the gathers below otherwise,
        recomputing them for every point.
        """
        left, width, log_w = self._table() if table is None else table
        nb = self.bins
        y = u * nb
        i = jnp.clip(jnp.floor(y).astype(jnp.int32), 0, nb - 1)
        frac = y - i
        # Scalar gathers (several times faster than one gather of table rows on the CPU).
        flat = i + nb * jnp.arange(self.dim, dtype=jnp.int32)
        gather = lambda t: t.at[flat].get(mode="promise_in_bounds")
        wi = gather(width)
        lo, hi = (jnp.reshape(b, (self.dim,)) for b in (self.lo, self.hi))
        x = jnp.clip(lo + (hi - lo) * (gather(left) + wi * frac), lo, hi)
        log_p = -_sum_last(gather(log_w)) - self._log_volume()
        return x, log_p, i

    def bin_index(self, x: jax.Array) -> jax.Array:
        """Per-axis bin index of points `(m, d)` -> `(m, d)` ints."""
        _, e = self._unit_edges()
        lo, hi = (jnp.reshape(b, (self.dim,)) for b in (self.lo, self.hi))
        t = (x - lo) / (hi - lo)
        idx = jax.vmap(
            lambda ej, tj: jnp.searchsorted(ej, tj, side="right") - 1, in_axes=(0, 1), out_axes=1
        )(e, t)
        return jnp.clip(idx, 0, self.bins - 1)

    def log_pdf(self, x):
        xm, batch = _as_matrix(self, x)
        w, _ = self._unit_edges()
        i = self.bin_index(xm)
        wi = w[jnp.arange(self.dim), i]
        lp = -jnp.sum(jnp.log(self.bins * wi), axis=-1) - self._log_volume()
        inside = jnp.all(
            (xm >= jnp.reshape(self.lo, (self.dim,))) & (xm <= jnp.reshape(self.hi, (self.dim,))),
            axis=-1,
        )
        return jnp.reshape(jnp.where(inside, lp, -jnp.inf), batch)

    def refine(self, x, weights, *, alpha: float = 0.5, counts=None) -> Grid:
        r"""One step of the VEGAS grid adaptation (Lepage 1978; vegas's `AdaptiveMap.adapt`).

        For each axis, `weights` (typically $(f(x)/p(x))^2$ per sample, times the
        sample's weight) are summed per bin to $d_i$ (divided by `counts` per bin
        if given), smoothed $d_i \leftarrow (d_{i-1} + 6 d_i + d_{i+1})/8$,
        normalised, and damped
        $$d_i \leftarrow \Big(\frac{1 - d_i}{\log(1/d_i)}\Big)^{\alpha};$$
        the new edges then split the piecewise-uniform "mass" $d$ into $N$ equal
        parts, so bins shrink where $|f|$ is large. `alpha = 0` leaves the grid
        unchanged; larger `alpha` adapts faster (vegas's default is 0.5).

        **Arguments:** `x` `(n, d)` (or `(n,)`) sample points; `weights` `(n,)`
        non-negative; `alpha` the damping exponent.

        **Returns:** the refined `Grid`.
        """
        if not isinstance(alpha, jax.core.Tracer) and not float(alpha) >= 0:
            raise ValueError(f"`alpha` must be >= 0, got {alpha}.")
        xm, batch = _as_matrix(self, x)
        weights = jnp.asarray(weights)
        if weights.shape != batch or len(batch) != 1:
            raise ValueError(
                f"`weights` must have shape {batch} matching `x`'s batch, got {weights.shape}."
            )
        return self._refine_bins(self.bin_index(xm), weights, alpha=alpha, counts=counts)

    def _refine_bins(self, index: jax.Array, weights: jax.Array, *, alpha, counts=None) -> Grid:
        """`refine` from the points' per-axis bin indices `(n, d)` (as `_map` returns them)."""
        weights = jnp.where(jnp.isfinite(weights), jnp.abs(weights), 0.0)
        nb = self.bins
        # One scatter for all axes: axis j's bin i is slot j * N + i.
        flat = index + nb * jnp.arange(self.dim, dtype=index.dtype)
        per_point = jnp.broadcast_to(weights[:, None], flat.shape)
        sums = jax.ops.segment_sum(
            jnp.reshape(per_point, (-1,)), jnp.reshape(flat, (-1,)), self.dim * nb
        )
        sums = jnp.reshape(sums, (self.dim, nb))
        if counts is not None:
            sums = sums / jnp.maximum(counts, 1)
        new_logits = jax.vmap(lambda s, lg: _vegas_rule(s, lg, alpha))(sums, self.logits)
        return eqx.tree_at(lambda g: g.logits, self, new_logits)


def _vegas_rule(d: jax.Array, logits: jax.Array, alpha) -> jax.Array:
    """New bin logits for one axis from per-bin weights `d` (see `Grid.refine`)."""
    nb = d.shape[0]
    w = jax.nn.softmax(logits)
    old = jnp.concatenate([jnp.zeros((1,), w.dtype), jnp.cumsum(w)])
    old = old / old[-1]
    if nb > 1:
        padded = jnp.concatenate([d[:1], d, d[-1:]])
        sm = (padded[:-2] + 6 * d + padded[2:]) / 8
    else:
        sm = d
    total = jnp.sum(sm)
    ok = total > 0
    sm = sm / jnp.where(ok, total, 1.0)
    tiny = jnp.finfo(sm.dtype).tiny
    pos = (sm > 0) & (sm < 1)
    safe = jnp.where(pos, sm, 0.5)
    damped = jnp.where(pos, ((1 - safe) / jnp.log(1 / safe)) ** alpha, jnp.where(sm >= 1, 1.0, 0.0))
    # Keep a floor so no bin collapses to zero width (and every region stays reachable).
    damped = jnp.maximum(damped, 1e-8 * jnp.max(damped) + tiny)
    cum = jnp.concatenate([jnp.zeros((1,), w.dtype), jnp.cumsum(damped)])
    targets = jnp.linspace(0.0, 1.0, nb + 1, dtype=w.dtype) * cum[-1]
    new = jnp.interp(targets, cum, old)
    new = new.at[0].set(0.0).at[-1].set(1.0)
    widths = jnp.maximum(jnp.diff(new), 1e-12)
    new_logits = jnp.log(widths / jnp.sum(widths))
    return jnp.where(ok, new_logits, logits)


class PiecewiseLinear(_MappedProposal):
    r"""A separable density that is piecewise linear along each axis.

    Axis $j$ of the unit box is cut into `bins` equal segments with knot heights
    $h_{jk} = e^{\theta_{jk}}$, $k = 0, \dots, K$; at $t = (k + s)/K$, $s \in [0, 1)$,
    the axis factor is the linear interpolant $q_j(t) = (1 - s)\,h_{jk} + s\,h_{j,k+1}$, and
    $$p(x) = \prod_j \frac{q_j(t_j)}{Z_j\,(hi_j - lo_j)},\qquad
    t_j = \frac{x_j - lo_j}{hi_j - lo_j},\quad Z_j = \sum_{k<K} \frac{h_{jk} + h_{j,k+1}}{2K}.$$

    It represents any product of per-axis piecewise-linear functions exactly: $f =
    \prod_i 2x_i$ on $[0,1]^d$ is $p$ itself with one segment and
    $h_{j0} \to 0$, so its importance estimator's variance goes to zero. Unlike
    `Grid`, whose density at a fixed point jumps when an edge moves past it, $p$
    is continuous in $\theta$, so `fit`'s BFGS on fixed samples works well.

    Sampling inverts each axis' CDF: the segment from the cumulative masses, then
    $s$ from $h_k s + (h_{k+1} - h_k) s^2/2 = K r$ ($r$ the mass left in the
    segment) by the cancellation-free root $s = 2Kr / (h_k + \sqrt{h_k^2 +
    2(h_{k+1} - h_k) K r})$, so samples are differentiable in $\theta$
    (reparameterised).

    **Fields:** `log_heights` `(d, K + 1)`, the parameters `fit` optimises
    (zeros: the uniform density).
    """

    lo: jax.Array
    hi: jax.Array
    log_heights: jax.Array

    def __init__(self, lo, hi, bins: int = 16):
        """**Arguments:** `lo`, `hi` the box (scalars or shape `(d,)`); `bins` the
        number of linear segments per axis $K$ (static int >= 1)."""
        self.lo, self.hi = check_bounds(lo, hi)
        bins = check_count(bins, "bins", minimum=1)
        d = 1 if jnp.ndim(self.lo) == 0 else jnp.shape(self.lo)[0]
        self.log_heights = jnp.zeros((d, bins + 1), self.lo.dtype)

    def __check_init__(self):
        if jnp.ndim(self.log_heights) != 2 or jnp.shape(self.log_heights)[0] != self.dim:
            raise ValueError(
                f"PiecewiseLinear needs log_heights of shape (d, bins + 1) = ({self.dim}, K + 1), "
                f"got {jnp.shape(self.log_heights)}."
            )

    @property
    def bins(self) -> int:
        return jnp.shape(self.log_heights)[1] - 1

    def _heights(self) -> tuple[jax.Array, jax.Array]:
        """Heights `(d, K+1)` (scaled so each axis' largest is 1) and cumulative masses `(d, K+1)`."""
        h = jnp.exp(self.log_heights - jnp.max(self.log_heights, axis=-1, keepdims=True))
        mass = (h[:, :-1] + h[:, 1:]) / (2 * self.bins)
        cum = jnp.concatenate([jnp.zeros_like(mass[:, :1]), jnp.cumsum(mass, axis=-1)], axis=-1)
        return h, cum

    def _at(self, table: jax.Array, k: jax.Array) -> jax.Array:
        """`table[j, k[:, j]]` for a `(d, K+1)` table and `(m, d)` segment indices."""
        return jnp.reshape(table, (-1,))[k + table.shape[1] * jnp.arange(self.dim)]

    def _log_axis_factor(self, h, cum, k, s):
        """$\\sum_j \\log(q_j / (Z_j (hi_j - lo_j)))$ at segment `k`, position `s` (both `(m, d)`)."""
        q = (1 - s) * self._at(h, k) + s * self._at(h, k + 1)
        log_z = jnp.log(cum[:, -1])
        return jnp.sum(jnp.log(q) - log_z, axis=-1) - jnp.sum(jnp.log(self.hi - self.lo))

    def map(self, u: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The inverse-CDF map: `u` `(m, d)` in $[0,1)^d$ to `x` `(m, d)` and `log_pdf(x)`."""
        h, cum = self._heights()
        target = u * cum[:, -1]
        k = jnp.sum(target[..., None] >= cum[:, 1:-1], axis=-1)
        h0, h1 = self._at(h, k), self._at(h, k + 1)
        r = (target - self._at(cum, k)) * self.bins
        disc = jnp.maximum(h0**2 + 2 * (h1 - h0) * r, 0.0)
        den = h0 + jnp.sqrt(disc)
        s = jnp.clip(2 * r / jnp.where(den > 0, den, 1.0), 0.0, 1.0)
        lo, hi = (jnp.reshape(b, (self.dim,)) for b in (self.lo, self.hi))
        x = jnp.clip(lo + (hi - lo) * (k + s) / self.bins, lo, hi)
        return x, self._log_axis_factor(h, cum, k, s)

    def log_pdf(self, x):
        xm, batch = _as_matrix(self, x)
        lo, hi = (jnp.reshape(b, (self.dim,)) for b in (self.lo, self.hi))
        t = (xm - lo) / (hi - lo) * self.bins
        k = jnp.clip(jnp.floor(t).astype(jnp.int32), 0, self.bins - 1)
        h, cum = self._heights()
        lp = self._log_axis_factor(h, cum, k, jnp.clip(t - k, 0.0, 1.0))
        inside = jnp.all((xm >= lo) & (xm <= hi), axis=-1)
        return jnp.reshape(jnp.where(inside, lp, -jnp.inf), batch)


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
            if not (callable(getattr(p, "sample", None)) and callable(getattr(p, "log_pdf", None))):
                raise TypeError(
                    f"`proposals[{i}]` must have sample(key, n) and log_pdf(x), got {type(p).__name__}."
                )
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
        k = jax.random.categorical(keys[0], self.log_weights, shape=(n,))
        xs = [p.sample(kk, n)[0] for p, kk in zip(self.proposals, keys[1:])]
        x = xs[0]
        for i, xi in enumerate(xs[1:], start=1):
            sel = k == i if self.event_ndim == 0 else (k == i)[:, None]
            x = jnp.where(sel, xi, x)
        return x, self.pdf(x)

    def _draw(self, key, n):
        """Stratified over components with weights `w_k / n_k` (exact gradients in `w`)."""
        counts = _allocate(n, len(self.proposals))
        if min(counts) < 1:
            raise ValueError(f"`n` must be at least the number of components, got {n}.")
        keys = jax.random.split(key, len(self.proposals))
        xs = [p.sample(kk, c)[0] for p, kk, c in zip(self.proposals, keys, counts)]
        x = jnp.concatenate(xs, axis=0)
        idx = jnp.concatenate([jnp.full((c,), i) for i, c in enumerate(counts)])
        w = jnp.exp(self._log_w())[idx] / jnp.asarray(counts, self.log_weights.dtype)[idx]
        return x, self.log_pdf(x), w


# The normalising flow and the partition live in their own modules (they subclass
# AbstractProposal).
from ._flow import Flow as Flow  # noqa: E402
from ._partition import Partition as Partition  # noqa: E402
