r"""A trained VEGAS grid mapped in powers of the distance to a face: QMC through it where
$f$ is singular on the box's faces (`"grid_qmc"` of `integrate(method="auto")`).

A grid's density is constant within a bin, so where $f \sim (x_j - lo_j)^{-a}$ near a face
(an integrable singularity, $0 < a < 1$) the values $f/q$ in the first bin grow without
bound: a power-law tail that no number of bins removes, and under which the spread of
QMC's replicas understates the error (`_auto`: QMC through such a grid is then no
candidate). `EdgedGrid` keeps the grid's bins, each of mass $1/N$, but maps each bin
linearly in $z = (x_j - lo_j)^{1/p}$ rather than in $x_j$: $x_j = lo_j + z^p$, and within a
bin

$$q(x) \propto \frac{dz}{dx} = \frac{1}{p}\,(x_j - lo_j)^{1/p - 1},$$

so with $p = 1/(1 - a)$ the density follows $f$ within every bin near the face, and $f/q$
is bounded. The bins on the axis' upper half measure the distance to $hi_j$ instead, with
a power of their own; an axis with $p = 1$ on both faces is the grid's.

The powers are read off the trained grid itself (`edge_powers`). At the fixed point of
VEGAS's refinement the bins carry equal shares of $|f|$'s marginal along each axis, whose
cumulative mass near a face goes as $x^{1-a}$: so the $k$-th edge from the face sits at
$e_k \propto k^{p}$, and $p$ is the slope of $\log e_k$ on $\log k$ over the edges
`EDGE_FIT`. The first edge is off the law (the trained first bin's mass is off its share):
it is left out of the fit, and the first `EDGE_FIT[1]` bins are laid evenly in $z$
(`_tables`). A corner singularity such as $(\sum x)^{-3/2}$ has bounded marginals, so its
slope reads near 1 and its axes stay linear (`EDGE_MIN_POWER`). A power under the true $p$
leaves $f/q \sim (x - lo)^{1/p_{true} - 1/p}$, a weaker singularity; one above it a density
that falls to zero at the face, and $f/q$ bounded: so the slope is raised by
`EDGE_OVERSHOOT`. With $f/q$ bounded, the values have no power-law tail, and QMC's replicas
through the bent grid estimate its error again.
"""
from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .._box import log_volume, to_box
from .._checks import is_concrete
from .._proposals._base import sum_last
from ..proposals import Grid


__all__ = ["BENT_REPLICAS", "EdgedGrid", "edge_powers", "edged"]

EDGE_FIT = (2, 16)  # the edges from each face, first and last, whose slope gives p
EDGE_MIN_POWER = 1.2  # a slope below this is no singularity (a <= 1/6): the bin stays linear
EDGE_OVERSHOOT = 1.2  # the slope, raised: a density that falls faster than f leaves f/q bounded
MAX_EDGE_POWER = 4.0  # a <= 3/4
MIN_EDGED_BINS = 4 * EDGE_FIT[1]  # (auto's grids hold 64 to 1024)
# QMC through a bent grid streams at least this many replicas (3 by default, `_plan`): the
# replicas' means are skewed there, and few of them understate the error (Student's t
# assumes normal means); the count was chosen on the project's benchmarks.
BENT_REPLICAS = 8
# A face is bent only where the box's coordinates resolve distances to it this small (in
# units of the box's width): in float32 only a face at 0 (see `edge_powers`).
MAX_FACE_SPACING = 1e-12


class EdgedGrid(eqx.Module):
    """A trained `Grid` mapped in the coordinates $z = (\\text{distance to a face})^{1/p}$ on
    each axis (see the module's docstring): powers `low`, `high` `(d,)` for the faces at
    `lo` and `hi` (1: the grid's own map on that half of the axis). Made by `edged`."""

    grid: Grid
    low: jax.Array
    high: jax.Array
    # Per (axis, bin), flattened to `(d * N,)`: z where u enters the bin and where it leaves
    # it, log(N p); and per axis the first bin measured from `hi` (`_tables`).
    start: jax.Array
    end: jax.Array
    log_scale: jax.Array
    split: jax.Array

    def __init__(self, grid: Grid, low, high):
        self.grid, self.low, self.high = grid, low, high
        self.start, self.end, self.log_scale, self.split = _tables(grid, low, high)

    @property
    def dim(self) -> int:
        return self.grid.dim

    @property
    def event_ndim(self) -> int:  # (0 for scalar bounds, as the grid's)
        return self.grid.event_ndim

    @property
    def lo(self) -> jax.Array:
        return self.grid.lo

    @property
    def hi(self) -> jax.Array:
        return self.grid.hi

    @property
    def powered(self) -> jax.Array:
        """Whether any axis maps with a power other than 1."""
        return jnp.any(self.low != 1) | jnp.any(self.high != 1)

    def map(self, u):
        """`(x, log q(x))` for unit points `u` `(n, d)`, as the grid's `map`; the grid's own
        where every power is 1 (a branch, so an unedged grid costs nothing more)."""
        powered = self.powered
        if is_concrete(powered):
            return self._map(u) if bool(powered) else self.grid.map(u)
        return jax.lax.cond(powered, lambda v: self._map(v), lambda v: self.grid.map(v), u)

    def _map(self, u):
        """The bent map: each coordinate linear in $z$ within its bin, $x$ its distance
        $z^p$ from the face (`split` says which), $q$ from the bin's slope and $z^{p-1}$."""
        grid = self.grid
        nb = grid.bins
        y = u * nb
        i = jnp.clip(jnp.floor(y).astype(jnp.int32), 0, nb - 1)
        flat = i + nb * jnp.arange(grid.dim, dtype=jnp.int32)
        gather = lambda table: table.at[flat].get(mode="promise_in_bounds")  # noqa: E731
        lower = i < self.split  # the distance is to `lo` (else to `hi`, falling as u grows)
        power = jnp.where(lower, self.low, self.high)
        # (The step is the difference of the two edges read here, exact: as `Grid`'s bins,
        # these tile their axis, whatever order the compiler summed the edges in.)
        start = gather(self.start)
        step = gather(self.end) - start
        z = jnp.maximum(start + step * (y - i), jnp.finfo(u.dtype).tiny)
        log_z = jnp.log(z)
        distance = jnp.exp(power * log_z)
        lo, hi = (jnp.reshape(b, (grid.dim,)) for b in (grid.lo, grid.hi))
        x = to_box(jnp.where(lower, distance, 1 - distance), lo, hi)
        # (`sum_last`: XLA on the CPU sums a short trailing axis slowly.)
        log_q = -sum_last(gather(self.log_scale) + jnp.log(jnp.abs(step)) + (power - 1) * log_z)
        return x, log_q - log_volume(grid.lo, grid.hi)


def _tables(grid: Grid, low, high):
    r"""`EdgedGrid`'s tables: per (axis, bin) $z$ where $u$ enters the bin and where it
    leaves it, and $\log(N\,p)$, flattened to `(d * N,)`; and per axis the first bin
    whose middle lies on the upper half, measured from `hi` (with `high`).

    Where a face has a power, the first `EDGE_FIT[1]` bins from it are even in $z$ (their
    edges follow the power law to the last of them, which stays): the trained first bin is
    off the law, and a corner of two such bins carries rare large values $f/q$ that QMC's
    replicas can all miss together, understating the error."""
    edges = grid._unit_edges()
    k = EDGE_FIT[1]
    even = jnp.arange(k + 1, dtype=edges.dtype) / k

    def z_edges(distance, power):  # (d, N + 1) distances from a face, increasing
        z = distance ** (1 / power[:, None])
        start = jnp.where(power[:, None] != 1, z[:, k:k + 1] * even, z[:, :k + 1])
        return jnp.concatenate([start, z[:, k + 1:]], axis=1)

    from_lo = z_edges(edges, low)
    from_hi = z_edges(1 - edges[:, ::-1], high)[:, ::-1]
    lower = edges[:, :-1] + edges[:, 1:] < 1  # the bin's middle on the lower half
    power = jnp.where(lower, low[:, None], high[:, None])
    start = jnp.where(lower, from_lo[:, :-1], from_hi[:, :-1])
    end = jnp.where(lower, from_lo[:, 1:], from_hi[:, 1:])
    flat = tuple(jnp.reshape(t, (-1,)) for t in (start, end, jnp.log(grid.bins * power)))
    return flat + (jnp.sum(lower, axis=1).astype(jnp.int32),)


@jax.jit
def edge_powers(grid: Grid) -> tuple[jax.Array, jax.Array]:
    r"""`(low, high)` `(d,)`: the power of each axis' first and last bin (`EdgedGrid`), the
    slope of $\log e_k$ on $\log k$ over the edges `EDGE_FIT` from that face, raised by
    `EDGE_OVERSHOOT` (at most `MAX_EDGE_POWER`), or 1 where the slope is below
    `EDGE_MIN_POWER` or unread (all 1 on a grid of fewer than `MIN_EDGED_BINS` bins).

    A face is bent only where the floats there are `MAX_FACE_SPACING` of the box's width
    apart or closer: a point nearer the face than their spacing rounds onto it (and `to_box`
    moves it inside), where the bent map would count mass no float can hold. In float32 at
    $hi = 1$ that is the $6 \times 10^{-8}$ nearest the face, 2.4e-4 of $(1 - x)^{-1/2}$'s
    integral, far more than the bent grid's error bar, which would not cover the missing
    mass. Through the grid alone that mass is missed as well, under error bars
    as wide as it. In float64 (spacing 2.2e-16 at 1) and at a face at 0 (any float type) it
    is 1.5e-8 of that integral or less."""
    edges = grid._unit_edges()
    nb = grid.bins
    if nb < MIN_EDGED_BINS:  # too few bins to read a law from
        ones = jnp.ones((grid.dim,), edges.dtype)
        return ones, ones
    k = jnp.arange(EDGE_FIT[0], EDGE_FIT[1] + 1)
    log_k = jnp.log(k.astype(edges.dtype))
    centred = log_k - jnp.mean(log_k)

    def power(distance):  # (d, K) distances of the edges k from the face
        log_e = jnp.log(distance)
        slope = jnp.sum((log_e - jnp.mean(log_e, axis=1, keepdims=True)) * centred, axis=1) \
            / jnp.sum(centred**2)
        singular = jnp.isfinite(slope) & (slope >= EDGE_MIN_POWER)
        return jnp.where(singular, jnp.minimum(EDGE_OVERSHOOT * slope, MAX_EDGE_POWER), 1.0)

    width = grid.hi - grid.lo
    resolved = [jnp.abs(jnp.spacing(face)) <= MAX_FACE_SPACING * width for face in (grid.lo, grid.hi)]
    low, high = (jnp.where(jnp.reshape(fine, (-1,)), power(distance), 1.0) for fine, distance
                 in zip(resolved, (edges[:, k], 1 - edges[:, nb - k])))
    return low, high


@jax.jit
def edged(grid: Grid) -> EdgedGrid:
    """The trained `grid` bent at the faces where it follows a singularity (`edge_powers`),
    for QMC through it: an `EdgedGrid` (`powered` says whether any face is bent)."""
    return EdgedGrid(grid, *edge_powers(grid))
