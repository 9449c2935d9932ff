"""The benchmark problems: integrands over a box with a known integral, each written once.

An integrand is `f(x, xp)`, with `xp` the array namespace (`jax.numpy` or
`numpy`) and `x` of shape `(..., d)`: one point `(d,)` for jaxmc, which vmaps,
or a batch `(n, d)` for vegas and SciPy. `Problem.jax_f` and `Problem.numpy_f`
bind the namespace. The suites choose which problems they run.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


@dataclasses.dataclass(frozen=True)
class Problem:
    """An integrand `f(x, xp)` on the box `[lo, hi]` and its integral `exact`."""

    name: str
    d: int
    f: Callable[[Any, Any], Any]
    exact: float
    lo: tuple[float, ...]
    hi: tuple[float, ...]
    separable: bool  # a product of one-dimensional factors (what VEGAS's grid adapts to)

    def jax_f(self, x):
        return self.f(x, jnp)

    def numpy_f(self, x):
        return self.f(x, np)


def _unit_cube(name: str, d: int, f: Callable, exact: float, *, separable: bool) -> Problem:
    return Problem(name, d, f, float(exact), (0.0,) * d, (1.0,) * d, separable)


def _gauss_box_integral(a, c, lo, hi):
    """∫_lo^hi exp(-a (x - c)^2) dx."""
    s = math.sqrt(a)
    return math.sqrt(math.pi / a) / 2 * (math.erf(s * (hi - c)) - math.erf(s * (lo - c)))


# ----------------------------------------------------------------------------
# Smooth integrands (the convergence suite): Genz (1984), Keister (1996), SciPy's example.


def _genz_shifts(d: int) -> np.ndarray:
    """Genz's shift parameters u_j in [0.3, 0.7]: a golden-ratio sequence, the same for every family."""
    return 0.3 + 0.4 * ((np.arange(d) * 0.6180339887) % 1.0)


def genz_oscillatory(d: int) -> Problem:
    r"""Genz's oscillatory family, $\cos(2\pi u_1 + a \cdot x)$, difficulty sum 9."""
    a = np.full(d, 9.0 / d)
    u1 = 0.3
    exact = (np.exp(2j * np.pi * u1) * np.prod((np.exp(1j * a) - 1) / (1j * a))).real

    def f(x, xp):
        return xp.cos(2 * np.pi * u1 + x @ xp.asarray(a))

    return _unit_cube(f"genz_oscillatory_d{d}", d, f, exact, separable=False)


def genz_gaussian(d: int) -> Problem:
    r"""Genz's Gaussian-peak family, $\exp(-\sum_j a_j^2 (x_j - u_j)^2)$, difficulty sum 7.25."""
    from scipy.special import erf

    a = np.full(d, 7.25 / d)
    u = _genz_shifts(d)
    exact = np.prod(np.sqrt(np.pi) / (2 * a) * (erf(a * (1 - u)) + erf(a * u)))

    def f(x, xp):
        return xp.exp(-xp.sum((xp.asarray(a) * (x - xp.asarray(u))) ** 2, axis=-1))

    return _unit_cube(f"genz_gaussian_d{d}", d, f, exact, separable=True)


def genz_product_peak(d: int) -> Problem:
    r"""Genz's product-peak family, $\prod_j (a_j^{-2} + (x_j - u_j)^2)^{-1}$, difficulty sum 7.25."""
    a = np.full(d, 7.25 / d)
    u = _genz_shifts(d)
    exact = np.prod(a * (np.arctan(a * (1 - u)) + np.arctan(a * u)))

    def f(x, xp):
        return xp.prod(1.0 / (xp.asarray(a) ** -2 + (x - xp.asarray(u)) ** 2), axis=-1)

    return _unit_cube(f"genz_product_peak_d{d}", d, f, exact, separable=True)


def genz_corner_peak(d: int) -> Problem:
    r"""Genz's corner-peak family, $(1 + a \cdot x)^{-(d+1)}$, difficulty sum 1.85.

    With all $a_j = a$ the integral is the $d$-th finite difference
    $\frac{1}{d!\,a^d} \sum_k \binom{d}{k} (-1)^k / (1 + k a)$, summed in exact
    rational arithmetic (in floating point it cancels badly at $d = 16$).
    """
    from fractions import Fraction

    a = 1.85 / d
    q = Fraction(a)  # the float's exact value
    total = sum(Fraction((-1) ** k * math.comb(d, k)) / (1 + k * q) for k in range(d + 1))
    exact = total / (math.factorial(d) * q**d)

    def f(x, xp):
        return (1.0 + a * xp.sum(x, axis=-1)) ** -(d + 1)

    return _unit_cube(f"genz_corner_peak_d{d}", d, f, float(exact), separable=False)


def genz_continuous(d: int) -> Problem:
    r"""Genz's continuous family, $\exp(-\sum_j a_j |x_j - u_j|)$ (a kink at $u$), difficulty sum 20.4."""
    a = np.full(d, 20.4 / d)
    u = _genz_shifts(d)
    exact = np.prod((2 - np.exp(-a * u) - np.exp(-a * (1 - u))) / a)

    def f(x, xp):
        return xp.exp(-xp.sum(xp.asarray(a) * xp.abs(x - xp.asarray(u)), axis=-1))

    return _unit_cube(f"genz_continuous_d{d}", d, f, exact, separable=True)


def genz_discontinuous(d: int) -> Problem:
    r"""Genz's discontinuous family: $\exp(a \cdot x)$ where $x_1 \le u_1$ and $x_2 \le u_2$, else 0.

    Difficulty sum 4.3; the jumps are on two axis-aligned hyperplanes.
    """
    a = np.full(d, 4.3 / d)
    u = _genz_shifts(d)
    cut = min(d, 2)
    upper = np.concatenate([u[:cut], np.ones(d - cut)])
    exact = np.prod(np.expm1(a * upper) / a)

    def f(x, xp):
        inside = x[..., 0] <= u[0]
        if cut == 2:
            inside = inside & (x[..., 1] <= u[1])
        return xp.where(inside, xp.exp(x @ xp.asarray(a)), 0.0)

    return _unit_cube(f"genz_discontinuous_d{d}", d, f, exact, separable=True)


def keister(d: int) -> Problem:
    """Keister's radial integrand mapped to the cube; its value by a 1-D radial quadrature."""
    from scipy import integrate, special

    radial = integrate.quad(
        lambda r: np.cos(r) * np.exp(-r * r) * r ** (d - 1), 0, np.inf,
        epsabs=1e-15, epsrel=1e-13, limit=200,
    )[0]
    exact = 2 * np.pi ** (d / 2) / special.gamma(d / 2) * radial

    def f(x, xp):
        # Clip to (0, 1) so a point exactly at 0 maps to a finite normal quantile.
        x = xp.clip(x, 2.0**-60, 1 - 2.0**-53)
        ndtri = special.ndtri if xp is np else jax.scipy.special.ndtri
        z = ndtri(x) / np.sqrt(2)
        return np.pi ** (d / 2) * xp.cos(xp.sqrt(xp.sum(z * z, axis=-1)))

    return _unit_cube(f"keister_d{d}", d, f, exact, separable=False)


def scipy_normal(d: int = 8) -> Problem:
    r"""SciPy's `qmc_quad` example: the standard normal density on the cube, $(\Phi(1) - 1/2)^d$."""
    from scipy.special import ndtr

    exact = (ndtr(1.0) - 0.5) ** d

    def f(x, xp):
        return (2 * np.pi) ** (-d / 2) * xp.exp(-0.5 * xp.sum(x * x, axis=-1))

    return _unit_cube(f"scipy_normal_d{d}", d, f, exact, separable=True)


# ----------------------------------------------------------------------------
# Peaked integrands (the adaptive suite): vegas's examples and i-flow's (Gao, Isaacson,
# Krause 2020).


def vegas_narrow_gaussian() -> Problem:
    """vegas's tutorial integrand: a narrow Gaussian, 4-D on [-1,1]x[0,1]^3, I = 1."""
    norm = 1013.2118364296088

    def f(x, xp):
        return xp.exp(-100.0 * xp.sum((x - 0.5) ** 2, axis=-1)) * norm

    return Problem("vegas narrow Gaussian", 4, f, 1.0, (-1.0, 0.0, 0.0, 0.0), (1.0,) * 4, True)


def diagonal_gaussians(name: str, d: int, centres: list[float]) -> Problem:
    r"""Gaussians $\exp(-100 |x - c|^2)$ centred on the diagonal of $[0,1]^d$, I = 1."""
    per = [_gauss_box_integral(100.0, c, 0.0, 1.0) ** d for c in centres]
    scale = 1.0 / sum(per)
    cs = np.asarray(centres)

    def f(x, xp):
        squared = xp.sum((x[..., None, :] - cs[:, None]) ** 2, axis=-1)  # (..., centres)
        return scale * xp.sum(xp.exp(-100.0 * squared), axis=-1)

    return _unit_cube(name, d, f, 1.0, separable=False)


def vegas_ridge() -> Problem:
    """vegas's ridge of 1000 Gaussians along the diagonal (examples/ridge.py), 4-D."""
    x0 = np.linspace(0.4, 0.6, 1000)
    norm = (100.0 / np.pi) ** 2

    def f(x, xp):
        squared = xp.sum((x[..., :, None] - x0) ** 2, axis=-2)  # (..., 1000)
        return xp.mean(xp.exp(-100.0 * squared), axis=-1) * norm

    return _unit_cube("ridge of 1000 Gaussians", 4, f, 0.999941839456619, separable=False)


IFLOW_ALPHA = 0.2  # i-flow's width of the Gaussian and the camel


def iflow_gaussian(d: int, alpha: float = IFLOW_ALPHA) -> Problem:
    """i-flow's Gaussian at the centre of the cube."""
    pre = (1.0 / (alpha * math.sqrt(math.pi))) ** d

    def f(x, xp):
        return pre * xp.exp(-xp.sum((x - 0.5) ** 2, axis=-1) / alpha**2)

    exact = math.erf(1 / (2 * alpha)) ** d
    return _unit_cube(f"i-flow Gaussian d={d}", d, f, exact, separable=True)


def iflow_camel(d: int, alpha: float = IFLOW_ALPHA) -> Problem:
    """i-flow's camel: two Gaussians on the diagonal, at 1/3 and 2/3."""
    pre = (1.0 / (alpha * math.sqrt(math.pi))) ** d

    def f(x, xp):
        return (
            0.5
            * pre
            * (
                xp.exp(-xp.sum((x - 1 / 3) ** 2, axis=-1) / alpha**2)
                + xp.exp(-xp.sum((x - 2 / 3) ** 2, axis=-1) / alpha**2)
            )
        )

    exact = (0.5 * (math.erf(1 / (3 * alpha)) + math.erf(2 / (3 * alpha)))) ** d
    return _unit_cube(f"i-flow camel d={d}", d, f, exact, separable=False)


def iflow_annulus(r1: float = 0.2, r2: float = 0.45) -> Problem:
    r"""i-flow's annulus: the indicator of $r_1 \le |x - c| \le r_2$ in the unit square."""

    def f(x, xp):
        squared = xp.sum((x - 0.5) ** 2, axis=-1)
        return xp.where((squared >= r1**2) & (squared <= r2**2), 1.0, 0.0)

    return _unit_cube("i-flow annulus d=2", 2, f, math.pi * (r2**2 - r1**2), separable=False)


# ----------------------------------------------------------------------------
# Shapes users bring (the auto suite): a correlated posterior, a resonance off the axes,
# integrable singularities and sharp edges. Each has a closed form (exact rational or
# 60-digit arithmetic where the inclusion-exclusion sums cancel in floating point).

# Points closer than this to a singularity are moved to it: the integral changes by
# O(TINY^(1-a)) ~ 1e-20 relative, and f stays finite in float64.
_SINGULAR_TINY = 2.0**-100


def correlated_gaussian(d: int = 5, sigma: float = 0.02, rho: float = 0.7) -> Problem:
    r"""A normalised Gaussian posterior with correlation `rho` between all pairs, I = 1.

    Means `linspace(0.4, 0.6, d)`, marginal widths `sigma`: its mass outside
    $[0, 1]^d$ is at most $\sum_j 2\Phi(-\min(\mu_j, 1 - \mu_j)/\sigma)$ (2.8e-88 at
    the defaults; checked below 1e-15), so the box integral is 1 in float64.
    """
    from scipy.special import ndtr

    mean = np.linspace(0.4, 0.6, d)
    cov = sigma**2 * ((1 - rho) * np.eye(d) + rho)
    precision = np.linalg.inv(cov)
    log_norm = -0.5 * (d * math.log(2 * math.pi) + np.linalg.slogdet(cov)[1])
    outside = float(np.sum(2 * ndtr(-np.minimum(mean, 1 - mean) / sigma)))
    if outside > 1e-15:
        raise ValueError(f"the Gaussian's mass outside the box ({outside:.2g}) is not negligible.")

    def f(x, xp):
        z = x - xp.asarray(mean)
        return xp.exp(log_norm - 0.5 * xp.sum(z * (z @ xp.asarray(precision)), axis=-1))

    return _unit_cube(f"correlated Gaussian d={d} (rho={rho})", d, f, 1.0, separable=False)


def _box_difference(d: int, w, antiderivative) -> Any:
    r"""$\int_{[0,1]^d} g(w \cdot x)\,dx = \sum_S (-1)^{d-|S|} G_d(w_S) / \prod_j w_j$.

    `antiderivative` is $G_d$, a $d$-fold antiderivative of $g$; the sum runs over the
    subsets $S$ of the axes, $w_S = \sum_{j \in S} w_j$. The caller picks the arithmetic
    (`Fraction`, mpmath) through `w` and `antiderivative`.
    """
    import itertools

    total = 0
    for corner in itertools.product((0, 1), repeat=d):
        w_s = sum((wj for wj, c in zip(w, corner) if c), start=0 * w[0])
        total += (-1) ** (d - sum(corner)) * antiderivative(w_s)
    return total / math.prod(w)


def oblique_resonance(d: int, width: float = 0.01) -> Problem:
    r"""A Breit-Wigner (Lorentzian) resonance across the cube, in $s = w \cdot x$ off the axes.

    $f(x) = \frac{\gamma / \pi}{(w \cdot x - m)^2 + \gamma^2}$ with $w \propto (1, \dots, 2)$
    a unit vector, $m = 0.4 \sum_j w_j$, $\gamma$ = `width`. Since
    $f = \operatorname{Im} \frac{1}{\pi (s - z)}$ with $z = m + i\gamma$, its $d$-fold
    antiderivative is $\frac{(s - z)^{d-1}}{(d-1)!}(\log(s - z) - H_{d-1})$ ($H$ the
    harmonic numbers), and the box integral follows by `_box_difference` in 60 digits.
    """
    import mpmath

    w = np.linspace(1.0, 2.0, d)
    w = w / np.linalg.norm(w)
    m = 0.4 * float(np.sum(w))
    with mpmath.workdps(60):
        z = mpmath.mpc(m, width)
        harmonic = sum(mpmath.mpf(1) / k for k in range(1, d))

        def antiderivative(s):
            u = s - z
            return u ** (d - 1) / mpmath.factorial(d - 1) * (mpmath.log(u) - harmonic)

        total = _box_difference(d, [mpmath.mpf(float(v)) for v in w], antiderivative)
        exact = float(mpmath.im(total) / mpmath.pi)

    def f(x, xp):
        s = x @ xp.asarray(w)
        return (width / np.pi) / ((s - m) ** 2 + width**2)

    return _unit_cube(f"oblique resonance d={d} (width {width})", d, f, exact, separable=False)


def power_singularity(d: int, a: float = 1 / 3) -> Problem:
    r"""$(1 - a)^d \prod_j x_j^{-a}$, singular on the faces through 0, I = 1.

    Finite variance for $a < 1/2$; at $a = 1/2$ the variance is infinite (an honest case:
    the error falls slower than $n^{-1/2}$ and the reported stderr is unreliable).
    """

    def f(x, xp):
        return (1 - a) ** d * xp.prod(xp.maximum(x, _SINGULAR_TINY) ** -a, axis=-1)

    return _unit_cube(f"x^-{a:.3g} product d={d}", d, f, 1.0, separable=True)


def corner_singularity(d: int, a: float = 1.5) -> Problem:
    r"""$(\sum_j x_j)^{-a}$, a point singularity at the corner 0, not separable.

    Integrable for $a < d$, finite variance for $2a < d$. Exact by `_box_difference`
    with $G_d(s) = s^{d-a} / \prod_{k=1}^d (k - a)$, in 60 digits (`a` not an integer).
    """
    import mpmath

    if a == int(a):
        raise ValueError(f"the closed form needs a non-integer exponent `a`, got {a}.")

    with mpmath.workdps(60):
        scale = mpmath.fprod(k - mpmath.mpf(a) for k in range(1, d + 1))
        exact = float(
            _box_difference(d, [mpmath.mpf(1)] * d, lambda s: s ** (d - mpmath.mpf(a)) / scale)
        )

    def f(x, xp):
        return xp.maximum(xp.sum(x, axis=-1), _SINGULAR_TINY) ** -a

    return _unit_cube(f"(sum x)^-{a:g} corner d={d}", d, f, exact, separable=False)


def ball_indicator(d: int, radius: float = 0.45) -> Problem:
    """The indicator of the ball of `radius` about the cube's centre: its volume."""
    exact = math.pi ** (d / 2) / math.gamma(d / 2 + 1) * radius**d

    def f(x, xp):
        return xp.where(xp.sum((x - 0.5) ** 2, axis=-1) <= radius**2, 1.0, 0.0)

    return _unit_cube(f"ball indicator d={d} (r={radius})", d, f, exact, separable=False)


def half_space_indicator(d: int, level: float = 0.3) -> Problem:
    r"""The indicator of $w \cdot x \le t$, $w = (1, 2, \dots, d)$, $t$ = `level` $\sum_j w_j$.

    A jump across an oblique hyperplane; the volume by `_box_difference` with
    $G_d(s) = (t - s)_+^d / d!$ (signs folded in), in exact rational arithmetic.
    """
    from fractions import Fraction

    w = np.arange(1.0, d + 1)
    t = Fraction(level) * int(np.sum(w))
    volume = _box_difference(
        d,
        [Fraction(int(v)) for v in w],
        lambda s: (-1) ** d * max(t - s, Fraction(0)) ** d / math.factorial(d),
    )
    threshold = float(t)

    def f(x, xp):
        return xp.where(x @ xp.asarray(w) <= threshold, 1.0, 0.0)

    return _unit_cube(f"half-space indicator d={d}", d, f, float(volume), separable=False)


# ----------------------------------------------------------------------------
# The coverage suite's extra shapes: a product of cosines, a normalised Gaussian of any
# width (down to a peak that a small budget misses) and a thin spherical shell.


def product_cos(d: int) -> Problem:
    r"""$\prod_j \cos x_j$ on $[0, 1]^d$, $I = \sin(1)^d$: smooth and separable."""

    def f(x, xp):
        return xp.prod(xp.cos(x), axis=-1)

    return _unit_cube(f"product cos d={d}", d, f, math.sin(1.0) ** d, separable=True)


def narrow_gaussian(d: int, sigma: float) -> Problem:
    r"""A normalised Gaussian of width `sigma` centred at Genz's shifts $u$ (off the grid lines).

    $f(x) = (2\pi\sigma^2)^{-d/2} \exp(-|x - u|^2 / 2\sigma^2)$, whose box integral is
    $\prod_j \frac12 [\mathrm{erf}((1 - u_j)/\sigma\sqrt2) + \mathrm{erf}(u_j/\sigma\sqrt2)]$.
    At $\sigma = 10^{-3}$ in 2-D the peak covers about $10^{-5}$ of the square, so a
    few thousand uniform points usually miss it altogether.
    """
    u = _genz_shifts(d)
    scale = sigma * math.sqrt(2.0)
    exact = math.prod(0.5 * (math.erf((1 - c) / scale) + math.erf(c / scale)) for c in u)
    norm = (2 * math.pi * sigma**2) ** (-d / 2)

    def f(x, xp):
        return norm * xp.exp(-xp.sum((x - xp.asarray(u)) ** 2, axis=-1) / (2 * sigma**2))

    return _unit_cube(f"narrow Gaussian d={d} (sigma={sigma:g})", d, f, exact, separable=True)


def thin_shell(d: int, radius: float = 0.3, width: float = 0.01) -> Problem:
    r"""The indicator of the shell $r \le |x - c| \le r + w$ about the cube's centre: its volume.

    $I = \frac{\pi^{d/2}}{\Gamma(d/2 + 1)} ((r + w)^d - r^d)$ (the shell lies inside the cube).
    """
    outer = radius + width
    if outer > 0.5:
        raise ValueError(f"the shell must lie inside the cube: radius + width = {outer} > 0.5.")
    exact = math.pi ** (d / 2) / math.gamma(d / 2 + 1) * (outer**d - radius**d)

    def f(x, xp):
        squared = xp.sum((x - 0.5) ** 2, axis=-1)
        return xp.where((squared >= radius**2) & (squared <= outer**2), 1.0, 0.0)

    return _unit_cube(f"thin shell d={d} (r={radius}, w={width})", d, f, exact, separable=False)
