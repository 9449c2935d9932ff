"""A separable density that is piecewise linear along each axis."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .._box import clip_to_open_box
from .._checks import check_bounds, check_count
from ._base import AbstractUnitMap, _as_matrix


class PiecewiseLinear(AbstractUnitMap):
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

    @classmethod
    def from_samples(
        cls, x, weights, lo, hi, bins: int = 16, *, iterations: int = 100, prior: float = 1.0
    ) -> PiecewiseLinear:
        r"""Fit the axis factors to weighted samples by expectation-maximisation.

        Along each axis the density is a mixture of the $K + 1$ normalised hat
        functions $\psi_m = B_m / \int B_m$ centred on the knots, with weights
        $\pi_m \propto h_m \int B_m$ ($\int B_m = 1/K$ inside, $1/(2K)$ at the
        ends). With samples $x_i$ and weights $w_i \ge 0$ summing to one (e.g.
        $|f(x_i)|/q(x_i)$, normalised), EM maximises $\sum_i w_i \log p(x_i)$ --
        the forward KL divergence from the weighted sample distribution to $p$,
        which for a product density splits into one problem per axis:
        $r_{im} = h_m B_m(t_i) / \sum_l h_l B_l(t_i)$, then
        $\pi_m = (\sum_i w_i r_{im} + \tau \int B_m)/(1 + \tau)$. The MAP term
        adds $\tau = \text{prior}/\text{ESS}$ of the uniform density
        ($\text{ESS} = 1/\sum_i w_i^2$), so no knot whose neighbourhood got no
        weight drops to zero height.

        **Arguments:** `x` `(m, d)` (or `(m,)` for scalar bounds); `weights` `(m,)`;
        `lo`, `hi` the box; `bins` $K$; `iterations` EM steps (static); `prior` as above.

        **Returns:** a `PiecewiseLinear`.
        """
        pl = cls(lo, hi, bins)
        iterations = check_count(iterations, "iterations", minimum=0)
        if not (isinstance(prior, (int, float)) and prior >= 0):
            raise ValueError(f"`prior` must be a number >= 0, got {prior!r}.")
        d, k_bins = pl.dim, pl.bins
        x = jnp.reshape(jnp.asarray(x, pl.lo.dtype), (-1, d))
        w = jnp.asarray(weights, pl.lo.dtype)
        if w.shape != x.shape[:1]:
            raise ValueError(
                f"`x` must have shape (m, {d}) and `weights` shape (m,), got {x.shape} and {w.shape}."
            )
        w = jnp.where(jnp.isfinite(w) & (w > 0), w, 0.0)
        w = w / jnp.maximum(jnp.sum(w), jnp.finfo(w.dtype).tiny)
        lo_v, hi_v = (jnp.reshape(b, (d,)) for b in (pl.lo, pl.hi))
        t = jnp.clip((x - lo_v) / (hi_v - lo_v), 0.0, 1.0) * k_bins
        k = jnp.clip(jnp.floor(t).astype(jnp.int32), 0, k_bins - 1)
        s = t - k
        area = jnp.full((k_bins + 1,), 1.0 / k_bins, w.dtype).at[jnp.array([0, -1])].set(
            0.5 / k_bins
        )
        tau = prior * jnp.sum(w**2)

        def em(h, _):
            # (m, d) responsibilities of the two knots of each sample's segment.
            h_lo, h_hi = jnp.take_along_axis(h.T, k, 0), jnp.take_along_axis(h.T, k + 1, 0)
            b_lo, b_hi = (1 - s) * h_lo, s * h_hi
            q = jnp.maximum(b_lo + b_hi, jnp.finfo(w.dtype).tiny)
            r_lo, r_hi = w[:, None] * b_lo / q, w[:, None] * b_hi / q
            mass = jax.vmap(
                lambda kj, a, b: jnp.zeros(k_bins + 1, w.dtype).at[kj].add(a).at[kj + 1].add(b),
                in_axes=1,
            )(k, r_lo, r_hi)  # (d, K + 1)
            pi = (mass + tau * area) / (1 + tau)
            h = pi / area
            return h / jnp.max(h, axis=-1, keepdims=True), None

        h0 = jnp.ones((d, k_bins + 1), w.dtype)
        h, _ = jax.lax.scan(em, h0, None, iterations)
        return eqx.tree_at(lambda p: p.log_heights, pl, jnp.log(h))

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
        """The inverse-CDF map: `u` `(m, d)` in $(0,1)^d$ to `x` `(m, d)` (open box), `log_pdf(x)`."""
        h, cum = self._heights()
        target = u * cum[:, -1]
        k = jnp.sum(target[..., None] >= cum[:, 1:-1], axis=-1)
        h0, h1 = self._at(h, k), self._at(h, k + 1)
        r = (target - self._at(cum, k)) * self.bins
        disc = jnp.maximum(h0**2 + 2 * (h1 - h0) * r, 0.0)
        den = h0 + jnp.sqrt(disc)
        s = jnp.clip(2 * r / jnp.where(den > 0, den, 1.0), 0.0, 1.0)
        lo, hi = (jnp.reshape(b, (self.dim,)) for b in (self.lo, self.hi))
        x = clip_to_open_box(lo + (hi - lo) * (k + s) / self.bins, lo, hi)
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

