"""Counting per cell: observed counts from a histogram, expected counts by quadrature
of the pdf, and Pearson's statistic over cells pooled up to a minimum expected count."""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_count
from ._domains import _Domain


def _make_bins(bins: Any, k: int) -> tuple[int, ...]:
    if isinstance(bins, (tuple, list)):
        if len(bins) != k:
            raise ValueError(f"`bins` must be an int or a sequence of {k} ints, got {bins!r}.")
        return tuple(check_count(b, "bins") for b in bins)
    return (check_count(bins, "bins"),) * k


def _histogram(dom: _Domain, x: jax.Array, bins: tuple[int, ...]):
    p, inside = dom.backward(x)
    inside = inside & jnp.all(jnp.isfinite(p), axis=-1)
    lo = jnp.broadcast_to(jnp.asarray(dom.lo, p.dtype), p.shape)
    hi = jnp.broadcast_to(jnp.asarray(dom.hi, p.dtype), p.shape)
    nb = jnp.broadcast_to(jnp.asarray(bins, jnp.int32), p.shape)
    idx = jnp.floor((p - lo) / (hi - lo) * nb.astype(p.dtype)).astype(jnp.int32)
    idx = jnp.clip(idx, 0, nb - 1)
    flat = idx[..., 0]
    for axis in range(1, len(bins)):
        flat = flat * bins[axis] + idx[..., axis]
    total = math.prod(bins)
    flat = jnp.where(inside, flat, total)
    counts = jnp.bincount(flat, length=total + 1)
    return counts[:total].reshape(bins), counts[total]


def _quadrature(dom: _Domain, bins: tuple[int, ...], order: int):
    """Tensor Gauss–Legendre nodes (`order` per axis per cell) and weights, cell by cell."""
    t, w = np.polynomial.legendre.leggauss(order)
    t, w = (t + 1.0) / 2.0, w / 2.0  # nodes and weights on [0, 1]
    k = len(bins)
    axes, weights = [], []
    for a in range(k):
        h = (dom.hi[a] - dom.lo[a]) / bins[a]
        edges = dom.lo[a] + h * np.arange(bins[a])
        axes.append((edges[:, None] + h * t[None, :]).ravel())  # (bins*order,)
        weights.append(np.tile(h * w, bins[a]))
    grids = np.meshgrid(*axes, indexing="ij")
    points = np.stack(grids, axis=-1).reshape(-1, k)
    wgt = weights[0]
    for a in range(1, k):
        wgt = np.multiply.outer(wgt, weights[a])
    return points, wgt


def _cell_integrals(integrand: np.ndarray, wgt: np.ndarray, bins: tuple[int, ...], order: int):
    """$\\int_{cell} p(x(t))\\,J(t)\\,dt$ per cell from the integrand at the nodes."""
    shape = []
    for b in bins:
        shape += [b, order]
    values = (integrand.reshape(wgt.shape) * wgt).reshape(shape)
    cells = values.sum(axis=tuple(range(1, 2 * len(bins), 2)))
    if not np.all(np.isfinite(cells)) or np.any(cells < 0):
        raise ValueError("`pdf` returned non-finite or negative values on the domain.")
    return cells


def _pool(observed: np.ndarray, expected: np.ndarray, min_expected: float):
    """Pearson's statistic with cells of expected count < `min_expected` pooled.

    As Mitsuba's `chi2`: sort the cells by expected count, merge the small ones
    (in increasing order) until each merged cell reaches `min_expected`; a
    remainder joins the smallest remaining cell. Cells with expected count 0
    are left out (samples there make the statistic infinite).
    Returns `(statistic, n_cells, n_pooled)`.
    """
    keep = expected > 0
    e = expected[keep]
    o = observed[keep].astype(np.float64)
    order = np.argsort(e, kind="stable")
    e, o = e[order], o[order]
    small = e < min_expected
    groups_e = list(e[~small])
    groups_o = list(o[~small])
    pooled_e: list[float] = []
    pooled_o: list[float] = []
    acc_e = acc_o = 0.0
    for ei, oi in zip(e[small], o[small]):
        acc_e += ei
        acc_o += oi
        if acc_e >= min_expected:
            pooled_e.append(acc_e)
            pooled_o.append(acc_o)
            acc_e = acc_o = 0.0
    if acc_e > 0:
        if groups_e:  # the smallest large cell (groups are in increasing order)
            groups_e[0] += acc_e
            groups_o[0] += acc_o
        elif pooled_e:
            pooled_e[-1] += acc_e
            pooled_o[-1] += acc_o
        else:
            pooled_e.append(acc_e)
            pooled_o.append(acc_o)
    ge = np.asarray(groups_e + pooled_e, dtype=np.float64)
    go = np.asarray(groups_o + pooled_o, dtype=np.float64)
    statistic = float(np.sum((go - ge) ** 2 / ge)) if ge.size else 0.0
    return statistic, int(ge.size), int(np.sum(small))
