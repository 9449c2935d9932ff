"""VEGAS's separable piecewise-constant density and its grid refinement rule."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp

from .._box import affine_to_box, log_volume, to_box
from .._checks import check_bounds, check_count, is_concrete
from ._base import AbstractUnitMap, _as_matrix, sum_last


class Grid(AbstractUnitMap):
    r"""VEGAS's separable piecewise-constant density (Lepage 1978, 2021).

    Each axis $j$ has `bins` bins with edges $lo_j = e_{j0} < \dots < e_{jN} = hi_j$;
    every bin carries probability $1/N$, so the density is
    $$p(x) = \prod_j \frac{1}{N\,\Delta_{j,i_j(x)}}$$
    where $\Delta_{ji}$ is the width of the bin of $x_j$. Sampling maps
    $u \in (0,1)^d$ through the piecewise-linear map $x_j = e_{ji} + \Delta_{ji}(Nu_j - i)$,
    $i = \lfloor N u_j\rfloor$, into the open box (never onto a face), so $x$ is
    differentiable in the widths. The widths are the softmax of unconstrained
    `logits` `(d, N)` (in units of the box width), so `fit` can optimise them;
    `refine` applies the classic VEGAS rule instead.

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
        bins = check_count(bins, "bins", minimum=1)
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

    def subdivided(self, factor: int) -> Grid:
        """The same density held in `factor` times as many bins, each bin split evenly
        (so that refining can go on at a finer resolution from where it stands)."""
        factor = check_count(factor, "factor", minimum=1)
        logits = jnp.repeat(self.logits, factor, axis=-1) - math.log(factor)
        return eqx.tree_at(lambda g: g.logits, self, logits)

    def _unit_edges(self) -> jax.Array:
        """Edges `(d, N+1)` in unit coordinates, from 0 to 1: the running sums of the widths,
        the last edge exactly 1 (the last bin takes the sums' rounding)."""
        w = jax.nn.softmax(self.logits, axis=-1)
        inner = jnp.cumsum(w[:, :-1], axis=-1)
        zero, one = jnp.zeros_like(w[:, :1]), jnp.ones_like(w[:, :1])
        return jnp.concatenate([zero, jnp.minimum(inner, 1), one], axis=-1)

    @property
    def edges(self) -> jax.Array:
        """Bin edges in the box's coordinates, `(d, N + 1)`."""
        e = self._unit_edges()
        lo = jnp.reshape(self.lo, (self.dim, 1))
        hi = jnp.reshape(self.hi, (self.dim, 1))
        return affine_to_box(e, lo, hi)

    def map(self, u: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The VEGAS map: `u` `(m, d)` in $(0,1)^d$ to `x` `(m, d)` (open box) and `log_pdf(x)`."""
        x, log_p, _ = self.map_with_bins(u)
        return x, log_p

    def lookup_table(self) -> tuple[jax.Array, jax.Array, jax.Array]:
        r"""Per (axis, bin), flattened to `(d * N,)`: left edge, width, and $\log(N\,\text{width})$.

        Each width is the difference of its bin's edges, not the softmax they were summed
        from: the two differ by about a unit of the edges' last place, a sizeable share of
        a narrow bin in float32, and bins whose extents and densities disagree overlap or
        leave gaps, a bias. The edges are sums, without a product the compiler could
        contract into the differences: those are exact, and the bins tile the interval.
        (A bin narrower than its edges' last place holds no interval: density infinite,
        f/p zero there, as the integral over it.)"""
        e = self._unit_edges()
        w = jnp.diff(e, axis=-1)
        log_w = jnp.log(w) + jnp.log(self.bins)
        return tuple(jnp.reshape(t, (-1,)) for t in (e[:, :-1], w, log_w))

    def map_with_bins(self, u: jax.Array, table=None) -> tuple[jax.Array, jax.Array, jax.Array]:
        """`map` plus each point's per-axis bin index `(m, d)`, which `refine` needs.

        `table` is `lookup_table()`, passed in by loops that keep it stored: XLA on the
        CPU fuses the table's softmax and logs into the gathers below otherwise,
        recomputing them for every point.
        """
        if table is None:  # materialised once, not fused into the gathers
            table = jax.lax.optimization_barrier(self.lookup_table())
        left, width, log_w = table
        nb = self.bins
        y = u * nb
        i = jnp.clip(jnp.floor(y).astype(jnp.int32), 0, nb - 1)
        frac = y - i
        # Scalar gathers (faster than one gather of table rows on the CPU).
        flat = i + nb * jnp.arange(self.dim, dtype=jnp.int32)
        gather = lambda t: t.at[flat].get(mode="promise_in_bounds")  # noqa: E731
        wi = gather(width)
        lo, hi = (jnp.reshape(b, (self.dim,)) for b in (self.lo, self.hi))
        x = to_box(gather(left) + wi * frac, lo, hi)  # never on a face, even if rounded there
        log_p = -sum_last(gather(log_w)) - log_volume(self.lo, self.hi)
        return x, log_p, i

    def bin_index(self, x: jax.Array) -> jax.Array:
        r"""Per-axis bin index of points `(m, d)` -> `(m, d)` ints: the last edge at or below
        each coordinate, clipped to the bins.

        A branchless binary search, all axes at once: $\lceil\log_2(N+1)\rceil$ steps,
        each one scalar gather from the flattened edges per coordinate: on a CPU much
        faster than `jnp.searchsorted` per axis.
        """
        e = self._unit_edges()
        flat_edges = jnp.reshape(e, (-1,))  # computed once, outside the search's loop
        lo, hi = (jnp.reshape(b, (self.dim,)) for b in (self.lo, self.hi))
        t = (x - lo) / (hi - lo)
        last = self.bins  # edges 0..N per axis
        row = (last + 1) * jnp.arange(self.dim, dtype=jnp.int32)
        steps = last.bit_length()  # probes 2^(steps-1), ..., 2, 1 from the left edge

        def probe(k, index):
            step = jnp.left_shift(jnp.int32(1), steps - 1 - k)
            at = jnp.minimum(index + step, last)
            return jnp.where(flat_edges.at[at + row].get(mode="promise_in_bounds") <= t, at, index)

        # A loop, so the index is stored between steps: unrolled, XLA fused each step with
        # the chain of earlier ones and recomputed it from their gathered edges.
        # (`zeros_like`: the carry keeps `t`'s type, varying over a `shard_map`'s axes.)
        index = jax.lax.fori_loop(0, steps, probe, jnp.zeros_like(t, dtype=jnp.int32))
        return jnp.clip(index, 0, self.bins - 1)

    def log_pdf(self, x):
        xm, batch = _as_matrix(self, x)
        _, _, log_w = self.lookup_table()
        # Materialised once: fused into the gather, the logs would be recomputed per point.
        log_w = jax.lax.optimization_barrier(log_w)
        flat = self.bin_index(xm) + self.bins * jnp.arange(self.dim, dtype=jnp.int32)
        lp = -sum_last(log_w.at[flat].get(mode="promise_in_bounds")) - log_volume(self.lo, self.hi)
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
        $$d_i \leftarrow \Big(\frac{1 - d_i}{\log(1/d_i)}\Big)^{\alpha},$$
        plus a defensive share $\rho = \min(1\%, 0.64/N)$ of the total spread evenly
        over the axis, $d_i \leftarrow d_i + \rho\,\Delta_i \sum_k d_k$ ($\Delta_i$ the
        bin's width in unit coordinates); the new edges then split the
        piecewise-uniform "mass" $d$ into $N$ equal parts, so bins shrink where
        $|f|$ is large. `alpha = 0` leaves the grid unchanged; larger `alpha`
        adapts faster (vegas's default is 0.5).

        The defensive share is not in vegas. Without it a region where no
        sample has landed (the zero side of a discontinuity) loses all its
        mass, and the bin next to it stretches across it and into the region
        where $f \ne 0$: that sliver is then sampled so rarely that most
        rounds never see its huge $f/p$, and their error bars are too small.
        Above 64 bins the share is the mass of 0.64 bins rather than 1%, so such a
        region keeps the same share of a bin at any $N$: at 1024 bins, 1% would
        hold ~10 bins away from where $f/p$ is large.

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
        return self.refine_bins(self.bin_index(xm), weights, alpha=alpha, counts=counts)

    def refine_bins(
        self, index: jax.Array, weights: jax.Array, *, alpha, counts=None, coarse_bins=None,
        coarse=True, point_weights=None,
    ) -> Grid:
        r"""`refine` from the points' per-axis bin indices `(n, d)` (as `map_with_bins` returns them).

        With `point_weights` `(n,)` (each point's share of the unit cube, e.g. $v/n_h$ in a
        stratified round), each bin's sum of `weights` is divided by its sum of
        `point_weights` (in place of `counts`): a ratio estimate of the bin's mean of
        $(f/p)^2$, free of the noise in how many points fell in it (as vegas's
        `sum_f / n_f`). On a fine grid with few points per bin that noise dominates the sums
        and distorts the map.

        With `coarse_bins` (a static divisor $M$ of `bins` $N$) and `coarse` (may be
        traced), the rule runs on $M$ groups of $N/M$ adjacent bins each and splits every
        new group evenly: a grid of $M$ bins, the same map, held in $N$ (so that a grid
        refined either way has one shape, `VegasPlus.coarse`).
        """
        weights = jnp.where(jnp.isfinite(weights), jnp.abs(weights), 0.0)
        nb = self.bins
        # One scatter for all axes: axis j's bin i is slot j * N + i.
        flat = index + nb * jnp.arange(self.dim, dtype=index.dtype)

        def per_bin(w):  # (n,) -> (d, N): each axis's bins' sums of w
            per_point = jnp.reshape(jnp.broadcast_to(w[:, None], flat.shape), (-1,))
            sums = jax.ops.segment_sum(per_point, jnp.reshape(flat, (-1,)), self.dim * nb)
            return jnp.reshape(sums, (self.dim, nb))

        sums = per_bin(weights)
        if point_weights is not None:
            counts = per_bin(jnp.asarray(point_weights, weights.dtype))
        counts = None if counts is None else jnp.broadcast_to(counts, (self.dim, nb))
        new_logits = _refined_logits(sums, counts, self.logits, alpha, 1)
        group = 1 if coarse_bins is None else _group_size(nb, coarse_bins)
        if group > 1:
            rough = _refined_logits(sums, counts, self.logits, alpha, group)
            new_logits = jnp.where(coarse, rough, new_logits)
        return eqx.tree_at(lambda g: g.logits, self, new_logits)


def _refined_logits(sums, counts, logits, alpha, group: int) -> jax.Array:
    """`_vegas_rule` on every axis, over groups of `group` adjacent bins (their sums, counts
    and widths), each new group's width split evenly over its bins."""
    if group > 1:
        grouped = lambda a: jnp.reshape(a, a.shape[:1] + (-1, group))  # noqa: E731
        sums = jnp.sum(grouped(sums), axis=-1)
        counts = None if counts is None else jnp.sum(grouped(counts), axis=-1)
        logits = jax.nn.logsumexp(grouped(logits), axis=-1)
    if counts is not None:  # (an empty bin's sum is 0: so is its mean)
        sums = sums / jnp.where(counts > 0, counts, 1)
    new = jax.vmap(lambda s, lg: _vegas_rule(s, lg, alpha))(sums, logits)
    return new if group == 1 else jnp.repeat(new - jnp.log(group), group, axis=-1)


def _group_size(bins: int, coarse_bins: int) -> int:
    if not 1 <= coarse_bins <= bins or bins % coarse_bins:
        raise ValueError(f"`coarse_bins` must divide the grid's {bins} bins, got {coarse_bins}.")
    return bins // coarse_bins


# The share of each refined axis's mass spread evenly over it (see `Grid.refine`): 1% at
# up to 64 bins, and the same mass in bins (0.64) above, so a region where f = 0 keeps the
# same fraction of a bin at any resolution without holding 1% of a fine grid away from f.
_DEFENSIVE_SHARE = 0.01
_DEFENSIVE_SHARE_BINS = 64


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
    # Keep a floor so no bin collapses to zero width (and every region stays reachable),
    # and a defensive share spread evenly in x (see `Grid.refine`).
    damped = jnp.maximum(damped, 1e-8 * jnp.max(damped) + tiny)
    share = _DEFENSIVE_SHARE * min(1, _DEFENSIVE_SHARE_BINS / nb)
    damped = damped + share * (w / jnp.sum(w)) * jnp.sum(damped)
    cum = jnp.concatenate([jnp.zeros((1,), w.dtype), jnp.cumsum(damped)])
    targets = jnp.linspace(0.0, 1.0, nb + 1, dtype=w.dtype) * cum[-1]
    new = jnp.interp(targets, cum, old)
    new = new.at[0].set(0.0).at[-1].set(1.0)
    widths = jnp.maximum(jnp.diff(new), 1e-12)
    new_logits = jnp.log(widths / jnp.sum(widths))
    return jnp.where(ok, new_logits, logits)

