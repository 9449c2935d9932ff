r"""A piecewise-constant density on an adaptive binary partition of the box.

`Partition` cuts the box recursively in halves, one axis at a time: a kd-tree
of dyadic cells, as in MISER (Press & Farrar 1990, recursive stratified
sampling) and Foam (Jadach 2003). Leaf $c$, a hyperrectangle of volume $V_c$,
carries probability $P_c$, so
$$p(x) = P_{c(x)} / V_{c(x)}.$$
Unlike the separable `Grid`, the cells follow an integrand's features wherever
they lie — edges, rings, ridges at any angle. The price is dimension: a
feature of codimension one needs on the order of $h^{1-d}$ cells at resolution
$h$, so partitions are for low dimensions.

`jaxmc.fit.adapt` samples a partition stratified — $n_c$ points uniform in
each leaf, $\hat I = \sum_c V_c \bar y_c$, $\hat V = \sum_c V_c^2 s_c^2/n_c$
(§4.2) — and grows it between rounds (the `PartitionGrowth` rule). Allocating
$n_c \propto V_c\sigma_c$ (Neyman) gives a per-sample variance
$(\sum_c V_c\sigma_c)^2$, so cells are split where $V_c\sigma_c$ is largest;
on an indicator only cells on the boundary have $\sigma_c > 0$, and the error
falls linearly with their size.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from .. import _random
from .._box import affine_to_box, as_vectors, to_box
from .._checks import check_bounds, check_count, check_key
from .._stats import slot_of_sample
from ._base import AbstractProposal, _as_matrix, _from_matrix


# Cells are dyadic: a cell's extent along an axis is 2^-level of the box's. Capped at
# 2^-20, so a float32 point (2^-24 resolution) still tells a cell's halves apart.
MAX_LEVEL = 20


class Partition(AbstractProposal):
    r"""A piecewise-constant density on a kd-tree of dyadic cells of the box.

    The box is cut recursively in halves along one axis at a time; leaf $c$, of
    volume $V_c$, carries probability $P_c = \operatorname{softmax}(\text{logits})_c$
    (over the leaves), so $p(x) = P_{c(x)}/V_{c(x)}$. `logits` are the
    parameters `fit` optimises; the tree is grown by `jaxmc.fit.adapt`, which
    samples the partition stratified (a fixed number of points in each leaf),
    splits, between rounds, the cells that contribute most to the estimator's
    error (see the module docstring), and sets $P_c \propto V_c\,
    \text{rms}_c(f)$ (the best importance density on these cells) mixed with
    $V_c$ at weight 0.1, so `sample` and `pdf` are a defensive i.i.d. density
    too.

    The tree lives in arrays of a fixed capacity, so a partition passes through
    `jit`, `vmap` and `lax.scan` while it grows: node $k$ is a leaf while
    `child[k] < 0`; otherwise it was halved along `axis[k]` into nodes
    `child[k]` (lower half) and `child[k] + 1`. Node $k$'s cell spans
    `corner[k, j] * 2**-level[k, j]` to `(corner[k, j] + 1) * 2**-level[k, j]`
    of the box along axis $j$. `size` nodes are in use.
    """

    lo: jax.Array
    hi: jax.Array
    logits: jax.Array  # (M,) log masses; only leaves count
    child: jax.Array  # (M,) int32
    axis: jax.Array  # (M,) int32
    corner: jax.Array  # (M, d) int32
    level: jax.Array  # (M, d) int32
    size: jax.Array  # () int32

    def __init__(self, lo, hi, max_cells: int = 1024):
        """**Arguments:**

        - `lo`, `hi`: the box (scalars or shape `(d,)`).
        - `max_cells`: the capacity in leaves (static int >= 1); the partition
          starts as one cell, the whole box.
        """
        self.lo, self.hi = check_bounds(lo, hi)
        max_cells = check_count(max_cells, "max_cells", minimum=1)
        d = 1 if jnp.ndim(self.lo) == 0 else jnp.shape(self.lo)[0]
        m = 2 * max_cells - 1
        self.logits = jnp.zeros((m,), self.lo.dtype)
        self.child = jnp.full((m,), -1, jnp.int32)
        self.axis = jnp.zeros((m,), jnp.int32)
        self.corner = jnp.zeros((m, d), jnp.int32)
        self.level = jnp.zeros((m, d), jnp.int32)
        self.size = jnp.ones((), jnp.int32)

    @property
    def max_cells(self) -> int:
        return (self.child.shape[0] + 1) // 2

    def is_leaf(self) -> jax.Array:
        """Whether each node `(M,)` is a leaf (a cell of the partition) in use."""
        return (self.child < 0) & (jnp.arange(self.child.shape[0]) < self.size)

    @property
    def n_cells(self) -> jax.Array:
        """Number of leaves (cells) in use."""
        return jnp.sum(self.is_leaf(), dtype=jnp.int32)

    def log_unit_volume(self) -> jax.Array:
        """$\\log V_k$ of every node as a fraction of the box, `(M,)`."""
        return -math.log(2.0) * jnp.sum(self.level, axis=-1).astype(self.logits.dtype)

    def log_box_volume(self) -> jax.Array:
        """$\\log$ of the box's volume."""
        return jnp.sum(jnp.log(jnp.reshape(self.hi - self.lo, (self.dim,))))

    def log_mass(self) -> jax.Array:
        """$\\log P_k$ of every node, `(M,)`: $-\\infty$ except at leaves."""
        return jax.nn.log_softmax(jnp.where(self.is_leaf(), self.logits, -jnp.inf))

    def unit_to_box(self, u: jax.Array) -> jax.Array:
        """Points of the unit cube `(n, d)` mapped into the open box (samples)."""
        return to_box(u, *as_vectors(self.lo, self.hi))

    def in_cells(self, node: jax.Array, r: jax.Array) -> jax.Array:
        """Points `r` `(n, d)` of the unit cube mapped into cells `node` `(n,)`, in unit coordinates."""
        return jnp.ldexp(self.corner[node].astype(r.dtype) + r, -self.level[node])

    def midpoint(self, node: jax.Array) -> jax.Array:
        """The midpoints of cells `node` along every axis, unit coordinates, `(n, d)`."""
        return jnp.ldexp(
            (2 * self.corner[node] + 1).astype(self.logits.dtype), -(self.level[node] + 1)
        )

    def locate(self, u: jax.Array) -> jax.Array:
        """The leaf containing each point `u` `(n, d)` of the unit cube, `(n,)`."""

        def descend(node):
            k = self.axis[node]
            mid = jnp.take_along_axis(self.midpoint(node), k[:, None], axis=1)[:, 0]
            below = jnp.take_along_axis(u, k[:, None], axis=1)[:, 0] < mid
            inner = self.child[node] >= 0
            return jnp.where(inner, self.child[node] + jnp.where(below, 0, 1), node)

        node = jnp.zeros(u.shape[:1], jnp.int32)
        return jax.lax.while_loop(lambda nd: jnp.any(self.child[nd] >= 0), descend, node)

    def log_pdf(self, x):
        xm, batch = _as_matrix(self, x)
        lo, hi = as_vectors(self.lo, self.hi)
        leaf = self.locate((xm - lo) / (hi - lo))
        lp = self.log_mass()[leaf] - self.log_unit_volume()[leaf] - self.log_box_volume()
        inside = jnp.all((xm >= lo) & (xm <= hi), axis=-1)
        return jnp.reshape(jnp.where(inside, lp, -jnp.inf), batch)

    def sample(self, key, n):
        key = check_key(key)
        n = check_count(n)
        k_cell, k_point = jax.random.split(key)
        log_mass = self.log_mass()
        cdf = jnp.cumsum(jnp.exp(log_mass))
        v = _random.uniform(k_cell, (n,), cdf.dtype) * cdf[-1]
        # side="right" skips cells of zero mass; the clip guards v rounding up to the total.
        last_leaf = jnp.max(jnp.where(self.is_leaf(), jnp.arange(cdf.shape[0]), 0))
        node = jnp.minimum(jnp.searchsorted(cdf, v, side="right"), last_leaf)
        u = self.in_cells(node, _random.uniform(k_point, (n, self.dim), self.lo.dtype))
        lp = log_mass[node] - self.log_unit_volume()[node] - self.log_box_volume()
        return _from_matrix(self, self.unit_to_box(u)), jnp.exp(lp)

    def leaves(self) -> tuple[jax.Array, jax.Array]:
        """The leaves' node indices in increasing order, padded to `max_cells`, and their count."""
        is_leaf = self.is_leaf()
        (ids,) = jnp.nonzero(is_leaf, size=self.max_cells, fill_value=0)
        return ids.astype(jnp.int32), jnp.sum(is_leaf, dtype=jnp.int32)

    def weighted_draw(self, key, n):
        r"""Stratified over the leaves, $n_c \approx n/L$ points each, weights $P_c/n_c$.

        `sum(w * g(x))` then depends on the masses exactly (so `fit` gets their
        gradients). With fewer than `n` cells every cell is visited.
        """
        ids, count = self.leaves()
        j = jnp.arange(self.max_cells)
        counts = jnp.where(j < count, (j + 1) * n // count - j * n // count, 0)
        node = ids[slot_of_sample(counts, n)]
        u = self.in_cells(node, _random.uniform(key, (n, self.dim), self.lo.dtype))
        log_mass = self.log_mass()[node]
        lp = log_mass - self.log_unit_volume()[node] - self.log_box_volume()
        w = jnp.exp(log_mass) / counts[slot_of_sample(counts, n)].astype(lp.dtype)
        return _from_matrix(self, self.unit_to_box(u)), lp, w

    def cells(self) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
        """Every node's cell in box coordinates: `(lower, upper, mass, is_leaf)`.

        Shapes `(M, d)`, `(M, d)`, `(M,)`, `(M,)` for the fixed capacity $M$ of
        nodes; only rows with `is_leaf` are cells of the partition (e.g. for
        plotting).
        """
        dtype = self.lo.dtype
        lo, hi = as_vectors(self.lo, self.hi)
        lower = affine_to_box(jnp.ldexp(self.corner.astype(dtype), -self.level), lo, hi)
        upper = affine_to_box(jnp.ldexp((self.corner + 1).astype(dtype), -self.level), lo, hi)
        return lower, upper, jnp.exp(self.log_mass()), self.is_leaf()

