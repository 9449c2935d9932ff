r"""A normalising flow on a box: coupling layers with rational-quadratic splines.

`Flow` is the density of neural importance sampling (Müller et al. 2019,
"Neural Importance Sampling", arXiv:1808.03856; Gao et al. 2020, "i-flow",
arXiv:2001.05486) with the monotone rational-quadratic (RQ) spline transforms
of Durkan et al. 2019, "Neural Spline Flows" (arXiv:1906.04032):

- the base density is uniform on the unit cube $[0,1]^d$;
- each coupling layer leaves the coordinates selected by a binary mask as they
  are and maps every other coordinate $z_j$ through a monotone RQ spline of
  $[0,1]$ onto itself, whose $K$ bin widths, $K$ bin heights and $K+1$ knot
  derivatives are the output of a small MLP of the unchanged coordinates;
- the unit cube is mapped affinely onto the box $[lo, hi]$.

A coupling layer's Jacobian is triangular, so
$\log p(x) = -\sum_\text{layers} \sum_j \log \partial_j s_j(z_j) - \sum_j
\log(hi_j - lo_j)$, exactly. Sampling runs the forward map from uniform $u$
(the samples are reparameterised: gradients with respect to the flow's
parameters flow through $x$); `log_pdf` runs the inverse map, solving each RQ
segment's quadratic in closed form (Durkan et al., eq. 6–8).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _random
from .._box import log_volume, to_box
from .._checks import check_bounds, check_count, check_key
from ._base import AbstractUnitMap


# Smallest bin width/height (as a fraction of [0, 1]) and knot derivative; they
# keep every slope of the spline, hence every log-det, bounded in float32.
_MIN_BIN_WIDTH = 1e-3
_MIN_BIN_HEIGHT = 1e-3
_MIN_DERIVATIVE = 1e-3


def _clip01(t: jax.Array) -> jax.Array:
    # Unlike `jnp.clip`, passes the full gradient at t = 0 and t = 1 (the faces
    # of the cube), where it only guards against rounding.
    return jnp.where(t < 0.0, 0.0, jnp.where(t > 1.0, 1.0, t))


def _softplus_inverse(y: float) -> float:
    return math.log(math.expm1(y))


# Raw derivative 0 must give derivative exactly 1 (together with equal widths and
# heights: the identity), so the zero-initialised flow is the uniform density.
_DERIVATIVE_SHIFT = _softplus_inverse(1.0 - _MIN_DERIVATIVE)


def _spline_knots(raw: jax.Array, bins: int):
    """Raw `(3K+1,)` parameters -> knot positions `(K+1,)`, heights `(K+1,)`, derivatives `(K+1,)`."""
    w_raw, h_raw, d_raw = raw[:bins], raw[bins : 2 * bins], raw[2 * bins :]
    widths = _MIN_BIN_WIDTH + (1.0 - _MIN_BIN_WIDTH * bins) * jax.nn.softmax(w_raw)
    heights = _MIN_BIN_HEIGHT + (1.0 - _MIN_BIN_HEIGHT * bins) * jax.nn.softmax(h_raw)
    derivatives = _MIN_DERIVATIVE + jax.nn.softplus(d_raw + _DERIVATIVE_SHIFT)
    zero = jnp.zeros((1,), raw.dtype)
    one = jnp.ones((1,), raw.dtype)
    # Pin the last knot to exactly 1 so the spline maps [0, 1] onto [0, 1].
    xs = jnp.concatenate([zero, jnp.cumsum(widths)[:-1], one])
    ys = jnp.concatenate([zero, jnp.cumsum(heights)[:-1], one])
    return xs, ys, derivatives


def _segment(knots: jax.Array, k: jax.Array):
    return knots[k], knots[k + 1] - knots[k]


def _rqs_forward(x: jax.Array, raw: jax.Array, bins: int) -> tuple[jax.Array, jax.Array]:
    """Monotone RQ spline of [0, 1] onto itself at scalar `x`; returns `(y, log dy/dx)`."""
    xs, ys, ds = _spline_knots(raw, bins)
    k = jnp.sum(x >= xs[1:-1])  # bin index in 0..K-1
    xk, wk = _segment(xs, k)
    yk, hk = _segment(ys, k)
    dk, dk1 = ds[k], ds[k + 1]
    sk = hk / wk
    xi = _clip01((x - xk) / wk)
    xi1 = xi * (1.0 - xi)
    den = sk + (dk1 + dk - 2.0 * sk) * xi1
    y = yk + hk * (sk * xi**2 + dk * xi1) / den
    dnum = sk**2 * (dk1 * xi**2 + 2.0 * sk * xi1 + dk * (1.0 - xi) ** 2)
    log_det = jnp.log(dnum) - 2.0 * jnp.log(den)
    return _clip01(y), log_det


def _rqs_inverse(y: jax.Array, raw: jax.Array, bins: int) -> tuple[jax.Array, jax.Array]:
    r"""Inverse of `_rqs_forward` at scalar `y`; returns `(x, log dx/dy)`.

    Solves $a\xi^2 + b\xi + c = 0$ on the segment with the cancellation-free root
    $\xi = 2c / (-b - \sqrt{b^2 - 4ac})$ (Durkan et al. 2019, eq. 6–8).
    """
    xs, ys, ds = _spline_knots(raw, bins)
    k = jnp.sum(y >= ys[1:-1])
    xk, wk = _segment(xs, k)
    yk, hk = _segment(ys, k)
    dk, dk1 = ds[k], ds[k + 1]
    sk = hk / wk
    dy = y - yk
    t = dk1 + dk - 2.0 * sk
    a = hk * (sk - dk) + dy * t
    b = hk * dk - dy * t
    c = -sk * dy
    disc = jnp.maximum(b**2 - 4.0 * a * c, 0.0)
    xi = _clip01(2.0 * c / (-b - jnp.sqrt(disc)))
    xi1 = xi * (1.0 - xi)
    den = sk + t * xi1
    dnum = sk**2 * (dk1 * xi**2 + 2.0 * sk * xi1 + dk * (1.0 - xi) ** 2)
    log_det = 2.0 * jnp.log(den) - jnp.log(dnum)
    return _clip01(xk + xi * wk), log_det


def _masks(d: int, layers: int) -> list[np.ndarray]:
    """Which coordinates each layer transforms (True) or conditions on (False).

    Binary-code masks as in i-flow: layer pair `b` splits the coordinates by bit
    `b` of their index, then the complement. Any two coordinates differ in some
    bit, so each pair ends up on opposite sides of some layer, and each
    coordinate is transformed by one layer of every pair.
    """
    if d == 1:
        return [np.ones(1, bool)] * layers
    bits = max(1, math.ceil(math.log2(d)))
    index = np.arange(d)
    masks = []
    for layer in range(layers):
        bit = (layer // 2) % bits
        mask = ((index >> bit) & 1).astype(bool)
        masks.append(mask if layer % 2 == 0 else ~mask)
    return masks


class _Coupling(eqx.Module):
    """One coupling layer; with no conditioning coordinates (d = 1), an unconditional spline."""

    conditioner: eqx.nn.MLP | None
    raw: jax.Array | None
    cond_idx: tuple[int, ...] = eqx.field(static=True)
    trans_idx: tuple[int, ...] = eqx.field(static=True)
    bins: int = eqx.field(static=True)

    def __init__(self, key, mask, bins, hidden, depth, activation, init_scale, dtype):
        self.cond_idx = tuple(int(i) for i in np.flatnonzero(~mask))
        self.trans_idx = tuple(int(i) for i in np.flatnonzero(mask))
        self.bins = bins
        n_out = len(self.trans_idx) * (3 * bins + 1)
        mlp_key, raw_key = jax.random.split(key)
        if self.cond_idx:
            mlp = eqx.nn.MLP(
                len(self.cond_idx),
                n_out,
                hidden,
                depth,
                activation=activation,
                key=mlp_key,
                dtype=dtype,
            )
            # A (near-)zero last layer makes the initial layer (near) the identity.
            last = mlp.layers[-1]
            mlp = eqx.tree_at(
                lambda m: (m.layers[-1].weight, m.layers[-1].bias),
                mlp,
                (init_scale * last.weight, jnp.zeros_like(last.bias)),
            )
            self.conditioner, self.raw = mlp, None
        else:
            self.conditioner = None
            self.raw = init_scale * jax.random.normal(raw_key, (n_out,), dtype)

    def _params(self, z: jax.Array) -> jax.Array:
        if self.conditioner is None:
            raw = self.raw
        else:
            # Centre the conditioning coordinates on 0 for the MLP.
            raw = self.conditioner(2.0 * z[np.asarray(self.cond_idx)] - 1.0)
        return raw.reshape(len(self.trans_idx), 3 * self.bins + 1)

    def _apply(self, z: jax.Array, spline: Callable) -> tuple[jax.Array, jax.Array]:
        raw = self._params(z)
        idx = np.asarray(self.trans_idx)
        y, log_det = jax.vmap(spline, in_axes=(0, 0, None))(z[idx], raw, self.bins)
        return z.at[idx].set(y), jnp.sum(log_det)

    def forward(self, z):
        return self._apply(z, _rqs_forward)

    def inverse(self, z):
        return self._apply(z, _rqs_inverse)


def _default_layers(d: int) -> int:
    return 2 if d == 1 else max(4, 2 * math.ceil(math.log2(d)))


class Flow(AbstractUnitMap):
    r"""A normalising flow on the box `[lo, hi]`: coupling layers of monotone
    rational-quadratic splines on the unit cube (neural importance sampling).

    The base density is uniform on $[0,1]^d$. Layer $l$ keeps the coordinates
    outside its mask, feeds them (centred, $2z-1$) to an `equinox.nn.MLP`, and
    maps each masked coordinate through an RQ spline of $[0,1]$ onto itself with
    `bins` bins; the MLP outputs each spline's `bins` widths, `bins` heights and
    `bins + 1` knot derivatives. The boundary derivatives (at 0 and 1) are free
    parameters like the interior ones -- on a bounded domain there are no
    identity tails to join -- so the density at the faces of the box is learned
    too. Masks split the coordinates by the bits of their index and alternate
    with their complements (as in i-flow), so every coordinate is transformed
    and every pair of coordinates interacts. For $d = 1$ each layer is an
    unconditional spline. Finally $x = lo + (hi - lo) z$.

    $$\log p(x) = -\sum_l \log\left|\det \partial T_l\right| - \sum_j \log(hi_j - lo_j)$$

    exactly, and zero outside the box. `sample` pushes uniform $u$ forward
    (reparameterised: gradients with respect to the parameters flow through
    $x$); `log_pdf` inverts each spline in closed form.

    References: Durkan, Bekasov, Murray, Papamakarios (2019), "Neural Spline
    Flows", arXiv:1906.04032; Müller, McWilliams, Rousselle, Gross, Novák
    (2019), "Neural Importance Sampling", arXiv:1808.03856; Gao, Isaacson,
    Krause (2020), "i-flow", arXiv:2001.05486.

    !!! Example

        ```python
        import jax, jax.numpy as jnp
        from jaxmc.proposals import Flow

        flow = Flow(jax.random.key(0), jnp.zeros(2), jnp.ones(2))
        x, pdf = flow.sample(jax.random.key(1), 1000)  # pdf ~ 1: near uniform at first
        ```
    """

    lo: jax.Array
    hi: jax.Array
    layers: tuple[_Coupling, ...]
    bins: int = eqx.field(static=True)

    def __init__(
        self,
        key: jax.Array,
        lo,
        hi,
        *,
        layers: int | None = None,
        bins: int = 16,
        hidden: int = 64,
        depth: int = 2,
        activation: Callable = jax.nn.silu,
        init_scale: float = 1e-2,
    ):
        r"""**Arguments:**

        - `key`: PRNG key for the initial parameters.
        - `lo`, `hi`: the box; scalars (one dimension; points are scalars) or of
          shape `(d,)`.
        - `layers`: number of coupling layers; default 2 for $d = 1$, else
          $\max(4, 2\lceil\log_2 d\rceil)$.
        - `bins`: number of spline bins $K \ge 2$.
        - `hidden`: width of the MLPs' hidden layers.
        - `depth`: number of hidden layers of each MLP.
        - `activation`: the MLPs' activation (smooth by default, which suits BFGS).
        - `init_scale`: scale of the MLPs' last-layer weights (their biases start
          at 0), i.e. how far the initial flow is from the identity; with 0 the
          initial density is exactly uniform. For $d = 1$, the standard
          deviation of the unconditional spline parameters.
        """
        key = check_key(key)
        self.lo, self.hi = check_bounds(lo, hi)
        d = 1 if self.lo.ndim == 0 else self.lo.shape[0]
        layers = _default_layers(d) if layers is None else check_count(layers, "layers")
        self.bins = check_count(bins, "bins", minimum=2)
        hidden = check_count(hidden, "hidden")
        depth = check_count(depth, "depth", minimum=0)
        if not callable(activation):
            raise TypeError(f"`activation` must be callable, got {type(activation).__name__}.")
        if not isinstance(init_scale, (int, float)) or not math.isfinite(init_scale):
            raise TypeError(f"`init_scale` must be a finite Python float, got {init_scale!r}.")
        if bins * max(_MIN_BIN_WIDTH, _MIN_BIN_HEIGHT) >= 1.0:
            raise ValueError(f"`bins` must be < {int(1 / _MIN_BIN_WIDTH)}, got {bins}.")
        keys = jax.random.split(key, layers)
        self.layers = tuple(
            _Coupling(k, m, bins, hidden, depth, activation, init_scale, self.lo.dtype)
            for k, m in zip(keys, _masks(d, layers), strict=True)
        )

    # -- maps of the unit cube, one point --------------------------------------

    def _forward_unit(self, u: jax.Array) -> tuple[jax.Array, jax.Array]:
        log_det = jnp.zeros((), u.dtype)
        for layer in self.layers:
            u, ld = layer.forward(u)
            log_det = log_det + ld
        return u, log_det

    def _inverse_unit(self, z: jax.Array) -> tuple[jax.Array, jax.Array]:
        log_det = jnp.zeros((), z.dtype)
        for layer in reversed(self.layers):
            z, ld = layer.inverse(z)
            log_det = log_det + ld
        return z, log_det

    def _as_points(self, x: jax.Array) -> tuple[jax.Array, tuple[int, ...]]:
        """Validate `x` and flatten it to `(m, d)`; returns it and the batch shape."""
        batch = self._batch_shape(x)
        x = jnp.asarray(x).astype(self.lo.dtype)
        return x.reshape((-1, self.dim)), batch

    def _to_box(self, z: jax.Array) -> jax.Array:
        # Into the open box, with the affine map's full gradient (also where z rounded to 0 or 1).
        return to_box(z, jnp.atleast_1d(self.lo), jnp.atleast_1d(self.hi))

    def _event(self, x: jax.Array, batch: tuple[int, ...]) -> jax.Array:
        return x.reshape(batch + jnp.shape(self.lo))

    # -- public maps ------------------------------------------------------------

    @eqx.filter_jit
    def forward(self, u: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The flow's map from the unit cube to the box: `u -> (x, log_pdf(x))`.

        `u` has the shape of a point (`(d,)`, or a scalar for scalar bounds) or
        a batch of them, in $[0, 1]$; `x` lies in the open box (never on a face).
        """
        u, batch = self._as_points(u)
        z, log_det = jax.vmap(self._forward_unit)(u)
        x = self._event(self._to_box(z), batch)
        return x, (-log_det - log_volume(self.lo, self.hi)).reshape(batch)

    @eqx.filter_jit
    def inverse(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The inverse map, `x -> (u, log_pdf(x))`; `log_pdf` is `-inf` outside the box."""
        x, batch = self._as_points(x)
        lo, hi = jnp.atleast_1d(self.lo), jnp.atleast_1d(self.hi)
        inside = jnp.all((x >= lo) & (x <= hi), axis=-1)
        z = _clip01((x - lo) / (hi - lo))
        u, log_det = jax.vmap(self._inverse_unit)(z)
        log_p = jnp.where(inside, log_det - log_volume(self.lo, self.hi), -jnp.inf)
        return self._event(u, batch), log_p.reshape(batch)

    # -- the proposal interface ------------------------------------------------------

    def sample(self, key, n):
        """Draw `n` points; returns `(x, pdf(x))` with `x` of shape `(n, d)` (or `(n,)`).

        Reparameterised: `x` is a differentiable function of the parameters for
        a fixed `key`.
        """
        key = check_key(key)
        n = check_count(n)
        x, log_p, _ = self.weighted_draw(key, n)
        return x, jnp.exp(log_p)

    def map(self, u: jax.Array) -> tuple[jax.Array, jax.Array]:
        """`forward` on a batch `u` `(m, d)` of the unit cube: `x` `(m, d)` and `log_pdf(x)`."""
        x, log_p = self.forward(u[:, 0] if self.event_ndim == 0 else u)
        return jnp.reshape(x, (-1, self.dim)), log_p

    @eqx.filter_jit
    def weighted_draw(self, key, n):
        # For `jaxmc.fit`: the reparameterised draw with its log density from the
        # forward pass, so no exp/log round trip underflows where p is tiny.
        key = check_key(key)
        n = check_count(n)
        u = _random.uniform(key, (n, self.dim), self.lo.dtype)
        x, log_p = self.forward(u[:, 0] if self.event_ndim == 0 else u)
        return x, log_p, jnp.full((n,), 1.0 / n, log_p.dtype)

    def log_pdf(self, x):
        """Log density w.r.t. Lebesgue measure, `-inf` outside the box; one point or a batch."""
        return self.inverse(x)[1]
