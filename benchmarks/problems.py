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
    u = 0.3 + 0.4 * ((np.arange(d) * 0.6180339887) % 1.0)
    exact = np.prod(np.sqrt(np.pi) / (2 * a) * (erf(a * (1 - u)) + erf(a * u)))

    def f(x, xp):
        return xp.exp(-xp.sum((xp.asarray(a) * (x - xp.asarray(u))) ** 2, axis=-1))

    return _unit_cube(f"genz_gaussian_d{d}", d, f, exact, separable=True)


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
