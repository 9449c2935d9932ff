"""Pearson's $\\chi^2$ goodness-of-fit test of a sampler against its claimed density."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_callable, check_count, check_key
from ._cells import _cell_integrals, _histogram, _make_bins, _pool, _quadrature
from ._domains import _domain_spec, _make_domain


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
