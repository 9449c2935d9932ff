r"""Statistical checks users can run on their own samplers.

`chi2_test` is Pearson's $\chi^2$ goodness-of-fit test of a sampler against
the density it claims to sample, the way Mitsuba tests its warps and BSDFs
(`mitsuba/python/chi2.py`, `ChiSquareTest`): histogram many samples on a grid
in a 2-D (or 1-D) parameterisation of the domain, integrate the pdf over every
cell numerically to get the expected counts, pool cells whose expected count
is below 5, and compare. A correct sampler gives a uniformly distributed
p-value; a wrong pdf, a missing Jacobian or a biased warp gives $p \approx 0$
once `n` is large enough. Run several such tests with a Bonferroni (or Šidák)
corrected significance level.

!!! Example

    ```python
    import jax, jaxmc

    def sample(key, n):
        return jaxmc.warps.hemisphere_cosine(jax.random.uniform(key, (n, 2)))

    stat, p = jaxmc.testing.chi2_test(
        jax.random.key(0), sample, jaxmc.warps.hemisphere_cosine_pdf,
        "hemisphere", n=100_000, bins=16)
    assert p > 1e-4
    ```
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._checks import check_callable, check_count, check_key


__all__ = ["chi2_test", "chi2_table", "Chi2Table"]

_DOMAINS = ("square", "disk", "sphere", "hemisphere", "triangle")
# Relative slack when deciding whether a sample lies in the domain (rounding).
_EPS = 1e-5


class Chi2Table(NamedTuple):
    """Everything `chi2_table` computed; `chi2_test` returns its first two fields.

    - `statistic`: Pearson's $\\chi^2 = \\sum (O - E)^2 / E$ over the pooled cells
      (`inf` if any sample fell where the pdf integrates to 0 or outside the domain).
    - `p_value`: $P(\\chi^2_{dof} \\ge$ `statistic`$)$.
    - `dof`: degrees of freedom, the number of cells after pooling minus 1.
    - `observed`, `expected`: counts per cell before pooling, shape `bins`.
    - `n_outside`: samples outside the domain or not finite.
    - `n_pooled`: cells with expected count below `min_expected` that were pooled.
    - `pdf_integral`: the pdf integrated over the domain (should be 1).
    """

    statistic: float
    p_value: float
    dof: int
    observed: np.ndarray
    expected: np.ndarray
    n_outside: int
    n_pooled: int
    pdf_integral: float

    def report(self, top: int = 10) -> str:
        """A readable summary with the `top` cells that contribute most to the statistic."""
        obs = self.observed.ravel().astype(np.float64)
        exp = self.expected.ravel()
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(exp > 0, (obs - exp) / np.sqrt(exp), np.where(obs > 0, np.inf, 0.0))
        lines = [
            f"chi2 = {self.statistic:.6g}, dof = {self.dof}, p = {self.p_value:.3g}, "
            f"samples outside the domain = {self.n_outside}, pooled cells = {self.n_pooled}, "
            f"pdf integral = {self.pdf_integral:.6f}",
            f"cells (shape {self.observed.shape}) with the largest |observed - expected|/sqrt(expected):",
        ]
        for flat in np.argsort(-np.abs(z))[:top]:
            cell = np.unravel_index(flat, self.observed.shape)
            lines.append(
                f"  cell {tuple(int(c) for c in cell)}: observed {int(obs[flat])}, "
                f"expected {exp[flat]:.2f}, z = {z[flat]:+.2f}"
            )
        return "\n".join(lines)


@dataclass(frozen=True)
class _Domain:
    """A parameterisation `p in [lo, hi]` (1-D or 2-D) of the sample space.

    `forward(p) -> (x, jacobian)` maps parameters to points with the density of
    the natural measure (`dx = jacobian dp`); `backward(x) -> (p, inside)`.
    """

    lo: np.ndarray
    hi: np.ndarray
    point_shape: tuple[int, ...]
    forward: Callable[[jax.Array], tuple[jax.Array, jax.Array]]
    backward: Callable[[jax.Array], tuple[jax.Array, jax.Array]]


def _direction(z, phi):
    s = jnp.sqrt(jnp.maximum((1.0 - z) * (1.0 + z), 0.0))
    return jnp.stack([s * jnp.cos(phi), s * jnp.sin(phi), z], axis=-1)


def _spherical(z_lo: float) -> _Domain:
    # (cos theta, phi): d omega = d(cos theta) d(phi), Jacobian 1.
    def forward(p):
        return _direction(p[..., 0], p[..., 1]), jnp.ones(p.shape[:-1], p.dtype)

    def backward(w):
        norm = jnp.linalg.norm(w, axis=-1)
        inside = (jnp.abs(norm - 1.0) <= 1e-3) & (w[..., 2] >= z_lo - _EPS)
        z = jnp.clip(w[..., 2] / norm, -1.0, 1.0)
        return jnp.stack([z, jnp.arctan2(w[..., 1], w[..., 0])], axis=-1), inside

    return _Domain(np.array([z_lo, -math.pi]), np.array([1.0, math.pi]), (3,), forward, backward)


def _disk() -> _Domain:
    # (r^2, phi): dA = r dr dphi = (1/2) d(r^2) dphi, so a uniform disk is uniform here.
    def forward(p):
        r = jnp.sqrt(p[..., 0])
        x = jnp.stack([r * jnp.cos(p[..., 1]), r * jnp.sin(p[..., 1])], axis=-1)
        return x, jnp.full(p.shape[:-1], 0.5, p.dtype)

    def backward(x):
        r2 = jnp.sum(x * x, axis=-1)
        inside = r2 <= 1.0 + _EPS
        return jnp.stack([r2, jnp.arctan2(x[..., 1], x[..., 0])], axis=-1), inside

    return _Domain(np.array([0.0, -math.pi]), np.array([1.0, math.pi]), (2,), forward, backward)


def _triangle() -> _Domain:
    # (s, t) in [0,1]^2 -> barycentrics (b0, b1) = (s, (1 - s) t); dA = (1 - s) ds dt.
    # The triangle's edge b0 + b1 = 1 is a grid line (t = 1), so cells never straddle it.
    def forward(p):
        s, t = p[..., 0], p[..., 1]
        return jnp.stack([s, (1.0 - s) * t], axis=-1), 1.0 - s

    def backward(b):
        b0, b1 = b[..., 0], b[..., 1]
        inside = (b0 >= -_EPS) & (b1 >= -_EPS) & (b0 + b1 <= 1.0 + _EPS)
        rest = 1.0 - b0
        t = jnp.where(rest > 0, b1 / jnp.where(rest > 0, rest, 1.0), 0.0)
        return jnp.stack([b0, t], axis=-1), inside

    return _Domain(np.array([0.0, 0.0]), np.array([1.0, 1.0]), (2,), forward, backward)


def _box(lo: np.ndarray, hi: np.ndarray) -> _Domain:
    scalar = lo.ndim == 0
    slack = _EPS * (hi - lo)

    def forward(p):
        x = p[..., 0] if scalar else p
        return x, jnp.ones(p.shape[:-1], p.dtype)

    def backward(x):
        p = x[..., None] if scalar else x
        low = jnp.broadcast_to(jnp.asarray(lo - slack, p.dtype), p.shape)
        high = jnp.broadcast_to(jnp.asarray(hi + slack, p.dtype), p.shape)
        inside = jnp.all((p >= low) & (p <= high), axis=-1)
        return p, inside

    shape = () if scalar else lo.shape
    return _Domain(np.atleast_1d(lo), np.atleast_1d(hi), shape, forward, backward)


def _domain_spec(domain: Any) -> str | tuple:
    """Validate `domain` and make it hashable: a name, or `(lo, hi)` as floats or float pairs."""
    if isinstance(domain, str):
        if domain not in _DOMAINS:
            raise ValueError(
                f"`domain` must be one of {_DOMAINS} or an interval (lo, hi), got {domain!r}."
            )
        return domain
    try:
        lo, hi = domain
        lo = np.asarray(lo, dtype=np.float64)
        hi = np.asarray(hi, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(
            f"`domain` must be one of {_DOMAINS} or a pair (lo, hi), got {domain!r}."
        ) from None
    if lo.shape != hi.shape or lo.ndim > 1 or lo.size > 2 or lo.size == 0:
        raise ValueError(
            "`domain` as (lo, hi) must be an interval (two scalars) or a rectangle (two "
            f"length-2 sequences), got lo={lo}, hi={hi}."
        )
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo < hi)):
        raise ValueError(f"`domain` (lo, hi) must be finite with lo < hi, got lo={lo}, hi={hi}.")
    if lo.ndim == 0:
        return (float(lo), float(hi))
    return (tuple(lo.tolist()), tuple(hi.tolist()))


@functools.lru_cache(maxsize=64)
def _make_domain(spec: str | tuple) -> _Domain:
    """The parameterisation of a validated domain (see `_domain_spec`)."""
    if spec == "square":
        return _box(np.zeros(2), np.ones(2))
    if spec == "disk":
        return _disk()
    if spec == "sphere":
        return _spherical(-1.0)
    if spec == "hemisphere":
        return _spherical(0.0)
    if spec == "triangle":
        return _triangle()
    lo, hi = spec
    return _box(np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64))


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


def _run(key, sample, pdf, spec, n, bins, order):
    """Sample, bin, and evaluate the pdf at the quadrature nodes.

    Compiled as one program by `_run_jit` with everything but `key` static, so
    repeating a test with the same `sample`, `pdf`, domain and sizes (e.g. over
    several keys) compiles once.
    """
    dom = _make_domain(spec)
    nodes, _ = _quadrature(dom, bins, order)
    x = jnp.asarray(sample(key, n))
    if x.shape != (n,) + dom.point_shape:
        raise ValueError(
            f"`sample(key, n)` must return shape {(n,) + dom.point_shape} for domain "
            f"{spec!r}, got {x.shape}."
        )
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    counts, outside = _histogram(dom, x, bins)
    points, jac = dom.forward(jnp.asarray(nodes, x.dtype))
    density = jnp.asarray(jax.vmap(pdf)(points))
    if density.shape != (nodes.shape[0],):
        raise ValueError(
            f"`pdf` must return one density per point, got shape {density.shape[1:]} "
            f"for a point of shape {dom.point_shape}."
        )
    return counts, outside, density * jac


_run_jit = jax.jit(_run, static_argnums=(1, 2, 3, 4, 5, 6))


def _hashable(f: Any) -> bool:
    try:
        hash(f)
    except TypeError:
        return False
    return True


def chi2_table(
    key: jax.Array,
    sample: Callable[[jax.Array, int], jax.Array],
    pdf: Callable[[jax.Array], jax.Array],
    domain: Any,
    *,
    n: int,
    bins: int | tuple[int, ...],
    quad_order: int = 6,
    min_expected: float = 5.0,
    jit: bool = True,
) -> Chi2Table:
    """`chi2_test` with all its diagnostics (observed and expected counts per cell).

    Same arguments as `chi2_test`; returns a `Chi2Table`, whose `report()`
    prints the worst cells, observed against expected.
    """
    key = check_key(key)
    check_callable(sample, "sample")
    check_callable(pdf, "pdf")
    n = check_count(n, "n")
    quad_order = check_count(quad_order, "quad_order")
    if not (isinstance(min_expected, (int, float)) and min_expected > 0):
        raise ValueError(f"`min_expected` must be a positive number, got {min_expected!r}.")
    spec = _domain_spec(domain)
    dom = _make_domain(spec)
    bins = _make_bins(bins, dom.lo.size)

    args = (sample, pdf, spec, n, bins, quad_order)
    if not jit:
        observed, outside, integrand = _run(key, *args)
    elif _hashable(sample) and _hashable(pdf):
        observed, outside, integrand = _run_jit(key, *args)
    else:  # e.g. bound methods of modules holding arrays: compile without the cache
        observed, outside, integrand = jax.jit(lambda k: _run(k, *args))(key)
    observed = np.asarray(observed, dtype=np.int64)
    outside = int(outside)
    _, wgt = _quadrature(dom, bins, quad_order)
    cells = _cell_integrals(np.asarray(integrand, dtype=np.float64), wgt, bins, quad_order)
    expected = n * cells
    statistic, n_cells, n_pooled = _pool(observed.ravel(), expected.ravel(), min_expected)
    dof = n_cells - 1
    if dof < 1:
        raise ValueError(
            f"Only {n_cells} cell(s) with expected count >= {min_expected} after pooling: "
            "increase `n` or `bins`."
        )
    impossible = outside > 0 or np.any(observed[expected <= 0] > 0)
    if impossible:
        statistic, p_value = math.inf, 0.0
    else:
        p_value = float(jax.scipy.special.gammaincc(dof / 2.0, jnp.asarray(statistic / 2.0)))
    return Chi2Table(
        statistic=float(statistic),
        p_value=p_value,
        dof=dof,
        observed=observed,
        expected=expected,
        n_outside=outside,
        n_pooled=n_pooled,
        pdf_integral=float(np.sum(cells)),
    )


def chi2_test(
    key: jax.Array,
    sample: Callable[[jax.Array, int], jax.Array],
    pdf: Callable[[jax.Array], jax.Array],
    domain: Any,
    *,
    n: int,
    bins: int | tuple[int, ...],
    quad_order: int = 6,
    min_expected: float = 5.0,
    jit: bool = True,
) -> tuple[float, float]:
    r"""Pearson's $\chi^2$ goodness-of-fit test of `sample` against `pdf`.

    Draws `x = sample(key, n)`, histograms it on a grid of `bins` cells in a
    parameterisation of `domain`, and compares with the expected counts
    $E_c = n \int_c p(x(\mathbf{t}))\,J(\mathbf{t})\,d\mathbf{t}$, computed by
    tensor Gauss–Legendre quadrature with `quad_order` nodes per axis inside each
    cell ($J$ is the Jacobian of the parameterisation). Cells with $E_c <$
    `min_expected` are pooled (Mitsuba's `ChiSquareTest` does the same), and
    the p-value is the $\chi^2$ survival function with (cells − 1) degrees of
    freedom, $Q(\tfrac{dof}{2}, \tfrac{\chi^2}{2})$ (regularised upper incomplete
    gamma, `jax.scipy.special.gammaincc`). Samples outside the domain, non-finite
    samples, or samples in a cell where the pdf integrates to 0 reject outright
    (`statistic = inf`, `p = 0`).

    Quadrature is exact enough for smooth densities; if the pdf jumps (a cone's
    rim, a tabulated density) put the jump on a grid line, or the expected counts
    of the cells it crosses are biased.

    **Arguments:**

    - `key`: a PRNG key, passed to `sample`.
    - `sample`: `sample(key, n) -> x`, `n` samples, shape `(n,)` for an interval,
      `(n, 2)` for `"square"`, `"disk"`, `"triangle"` and rectangles, `(n, 3)`
      (unit vectors) for `"sphere"`, `"hemisphere"`. To test a warp, draw the
      uniforms inside: `lambda key, n: warp(jax.random.uniform(key, (n, 2)))`.
    - `pdf`: the claimed density for one point, w.r.t. the natural measure
      (length, area, solid angle); it is `vmap`ped over points, so a pdf that
      already broadcasts over batch axes works too.
    - `domain`: `"square"` ($[0,1]^2$, histogram in $(x, y)$), `"disk"` (unit
      disk, in $(r^2, \phi)$), `"sphere"` or `"hemisphere"` (around $+z$, in
      $(\cos\theta, \phi)$), `"triangle"` (barycentrics $(b_0, b_1)$ of the
      reference triangle, in $(b_0, b_1/(1 - b_0))$), an interval `(lo, hi)`
      of scalars, or a rectangle `((x0, y0), (x1, y1))`.
    - `n`: number of samples (a Python int).
    - `bins`: cells per parameter axis, an int or one int per axis.
    - `quad_order`: Gauss–Legendre nodes per axis per cell.
    - `min_expected`: pooling threshold on expected counts (default 5).
    - `jit`: compile sampling, binning and the pdf with `jax.jit` (cached on
      `sample`, `pdf`, `domain` and the sizes, so repeated tests of the same
      functions compile once); pass `False` for a `sample` that is not
      traceable (e.g. NumPy code). `pdf` is always `vmap`ped, so it must be
      written with `jax.numpy`.

    **Returns:** `(statistic, p_value)` as Python floats. Use `chi2_table` for
    the degrees of freedom and the observed and expected counts.
    """
    table = chi2_table(
        key, sample, pdf, domain, n=n, bins=bins, quad_order=quad_order,
        min_expected=min_expected, jit=jit,
    )
    return table.statistic, table.p_value
