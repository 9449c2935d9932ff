r"""Problems of kinds the `auto` suite's tuning half lacks, for its validation half.

Smooth integrands in 24-64 dimensions, rendering integrals (irradiance and a form factor),
posteriors with several parameters, singular sets that are neither a face nor a corner of
the box, and boxes that are not the unit cube. Each integral is a closed form, or a
one- or two-dimensional reduction of it integrated to near machine precision.
"""

from __future__ import annotations

import functools
import itertools
import math

import numpy as np

from .problems import _SINGULAR_TINY, Problem, genz_oscillatory, product_cos


def smooth_high_dimensional() -> list[Problem]:
    """Genz's oscillatory family in 32-D and a product of cosines in 48-D."""
    return [genz_oscillatory(32), product_cos(48)]


def _rectangle_irradiance(x, y, h):
    r"""$\int_0^x\int_0^y h^2/(u^2 + v^2 + h^2)^2\,du\,dv$: the irradiance at a point a
    height $h$ below one corner of an $x \times y$ Lambertian emitter of unit radiance."""
    a, b = math.hypot(x, h), math.hypot(y, h)
    return 0.5 * (x / a * math.atan(y / a) + y / b * math.atan(x / b))


def irradiance(x0=-0.3, x1=1.7, y0=-1.2, y1=0.4, h=0.5) -> Problem:
    r"""The irradiance at the origin from a rectangular light $[x_0, x_1] \times [y_0, y_1]$ a
    height $h$ above, parallel to the receiver: $\int h^2/(x^2 + y^2 + h^2)^2\,dA$ over the
    light's area (a 2-D rendering integral on a box that is not the unit square)."""
    def corner(x, y):  # odd in each argument, as the integrand is even
        return math.copysign(1, x) * math.copysign(1, y) * _rectangle_irradiance(abs(x), abs(y), h)

    exact = corner(x1, y1) - corner(x0, y1) - corner(x1, y0) + corner(x0, y0)

    def f(x, xp):
        r2 = x[..., 0] ** 2 + x[..., 1] ** 2 + h**2
        return h**2 / r2**2

    return Problem("irradiance from a rectangle", 2, f, exact, (x0, y0), (x1, y1), False)


@functools.cache
def _parallel_squares_form_factor(h: float) -> float:
    r"""$\int\int h^2 / \pi (|u|^2 + h^2)^2$ over two parallel unit squares a distance $h$
    apart, by its reduction to the difference $u = x - x'$: $\int_{[-1,1]^2} (1 - |u_1|)
    (1 - |u_2|) h^2 / \pi(|u|^2 + h^2)^2\,du$, on the quadrant by symmetry."""
    from scipy.integrate import dblquad

    value, _ = dblquad(lambda v, u: 4 * (1 - u) * (1 - v) * h**2 / (math.pi * (u * u + v * v + h * h) ** 2),
                       0, 1, 0, 1, epsabs=1e-15, epsrel=1e-13)
    return value


def form_factor(h: float = 0.25) -> Problem:
    """The form factor between two parallel unit squares a distance `h` apart: a 4-D
    rendering integral over both squares' areas, sharp where the squares face each other."""

    def f(x, xp):
        r2 = (x[..., 0] - x[..., 2]) ** 2 + (x[..., 1] - x[..., 3]) ** 2 + h**2
        return h**2 / (math.pi * r2**2)

    return Problem(f"form factor of parallel squares (h={h})", 4, f,
                   _parallel_squares_form_factor(h), (0.0,) * 4, (1.0,) * 4, False)


def rotated_gaussian(d: int = 8, seed: int = 1) -> Problem:
    r"""A posterior with `d` parameters: a normalised Gaussian with a random covariance
    (eigenvalues from $0.01^2$ to $0.04^2$, random axes) at a random centre in
    $[0.4, 0.6]^d$; its mass outside the unit cube is negligible."""
    from scipy.special import ndtr

    rng = np.random.default_rng(seed)
    axes, _ = np.linalg.qr(rng.standard_normal((d, d)))
    cov = axes @ np.diag(np.linspace(0.01, 0.04, d) ** 2) @ axes.T
    mean = rng.uniform(0.4, 0.6, d)
    precision = np.linalg.inv(cov)
    log_norm = -0.5 * (d * math.log(2 * math.pi) + np.linalg.slogdet(cov)[1])
    sd = np.sqrt(np.diag(cov))
    if float(np.sum(2 * ndtr(-np.minimum(mean, 1 - mean) / sd))) > 1e-15:
        raise ValueError("the Gaussian's mass outside the box is not negligible.")

    def f(x, xp):
        z = x - xp.asarray(mean)
        return xp.exp(log_norm - 0.5 * xp.sum(z * (z @ xp.asarray(precision)), axis=-1))

    return Problem(f"rotated Gaussian posterior d={d}", d, f, 1.0, (0.0,) * d, (1.0,) * d,
                   False)


def banana(d: int = 4, b: float = 8.0, s: float = 0.05) -> Problem:
    r"""A curved posterior (Haario's twisted Gaussian) with `d` parameters: $y_2 = x_2 +
    b((x_1 - \frac12)^2 - s^2)$ and the other coordinates as they are, Gaussian in $y$
    (widths $2s$ on the first axis, $s$ on the rest) about the cube's centre. The map has a
    unit Jacobian; its arms reach out of the box, so the integral is the mass inside:
    $\int N(z_1; 2s)\,[\Phi(\cdot) - \Phi(\cdot)]\,dz_1$ over the first axis (quadrature
    to near machine precision) times the other axes' Gaussian masses."""
    from scipy.integrate import quad
    from scipy.special import ndtr

    widths = np.asarray([2 * s] + [s] * (d - 1))
    log_norm = -0.5 * d * math.log(2 * math.pi) - float(np.sum(np.log(widths)))

    def bent_mass(z0):  # the second axis' mass inside the box, given the first
        shift = b * (z0 * z0 - s * s)
        return ndtr((0.5 + shift) / s) - ndtr((-0.5 + shift) / s)

    first, _ = quad(lambda z0: math.exp(-0.5 * (z0 / (2 * s)) ** 2) / (2 * s * math.sqrt(2 * math.pi))
                    * bent_mass(z0), -0.5, 0.5, epsabs=1e-14, epsrel=1e-12, limit=200)
    exact = first * float(ndtr(0.5 / s) - ndtr(-0.5 / s)) ** (d - 2)

    def f(x, xp):
        z = x - 0.5
        bent = z[..., 1] + b * (z[..., 0] ** 2 - s**2)
        y = xp.concatenate([z[..., :1], bent[..., None], z[..., 2:]], axis=-1)
        return xp.exp(log_norm - 0.5 * xp.sum((y / xp.asarray(widths)) ** 2, axis=-1))

    return Problem(f"banana posterior d={d}", d, f, exact, (0.0,) * d, (1.0,) * d, False)


def _inverse_distance_antiderivative(x, y, z):
    r"""$F$ with $\partial_x\partial_y\partial_z F = 1/\sqrt{x^2 + y^2 + z^2}$ (the potential
    of a uniform box: Waldvogel 1976)."""
    r = math.sqrt(x * x + y * y + z * z)

    def log_term(a, b, c):
        return b * c * math.log(a + r) if b and c and r + a > 0 else 0.0

    def angle_term(a, b, c):
        return 0.5 * a * a * math.atan(b * c / (a * r)) if a and r else 0.0

    return (log_term(x, y, z) + log_term(y, x, z) + log_term(z, x, y)
            - angle_term(x, y, z) - angle_term(y, x, z) - angle_term(z, x, y))


def coulomb(centre=(0.3, 0.45, 0.6)) -> Problem:
    r"""$1/|x - c|$ in the unit cube, $c$ inside: a point singularity in the interior (the
    potential at $c$ of the cube's uniform charge), with finite variance ($f^2 = r^{-2}$
    against the volume element $r^2\,dr$)."""
    exact = 0.0
    for corner in itertools.product((0, 1), repeat=3):
        sign = (-1) ** (3 - sum(corner))
        exact += sign * _inverse_distance_antiderivative(*(k - c for k, c in zip(corner, centre)))
    c = np.asarray(centre)

    def f(x, xp):
        return 1 / xp.maximum(xp.sqrt(xp.sum((x - c) ** 2, axis=-1)), _SINGULAR_TINY)

    return Problem("1/|x - c| inside the cube", 3, f, exact, (0.0,) * 3, (1.0,) * 3, False)


def singular_circle(r: float = 0.25, outer: float = 0.4, a: float = 1 / 3) -> Problem:
    r"""$|\rho - r|^{-a}$ for $\rho = |x - c| < R$ (0 beyond), $c$ the square's centre: a
    singularity along a circle, neither a face nor a corner, with finite variance for
    $a < 1/2$; $\int = 2\pi\int_0^R |\rho - r|^{-a}\rho\,d\rho$."""
    d = outer - r
    inner = r ** (2 - a) / (1 - a) - r ** (2 - a) / (2 - a)  # int_0^r (r - p)^-a p dp
    beyond = d ** (2 - a) / (2 - a) + r * d ** (1 - a) / (1 - a)  # int_r^R (p - r)^-a p dp
    exact = 2 * math.pi * (inner + beyond)

    def f(x, xp):
        rho = xp.sqrt(xp.sum((x - 0.5) ** 2, axis=-1))
        value = xp.maximum(xp.abs(rho - r), _SINGULAR_TINY) ** -a
        return xp.where(rho < outer, value, 0.0)

    return Problem("singular circle d=2", 2, f, exact, (0.0,) * 2, (1.0,) * 2, False)


def anisotropic_peak() -> Problem:
    r"""A Gaussian peak on the box $[-3, 7] \times [0, 100] \times [-1, 1]$ with widths 0.5,
    5 and 0.1 in the units of each axis, off the box's centre."""
    lo, hi = np.asarray([-3.0, 0.0, -1.0]), np.asarray([7.0, 100.0, 1.0])
    centre, width = np.asarray([1.0, 62.0, 0.2]), np.asarray([0.5, 5.0, 0.1])
    exact = math.prod(
        0.5 * width[j] * math.sqrt(2 * math.pi)
        * (math.erf((hi[j] - centre[j]) / (width[j] * math.sqrt(2)))
           - math.erf((lo[j] - centre[j]) / (width[j] * math.sqrt(2))))
        for j in range(3)
    )

    def f(x, xp):
        return xp.exp(-0.5 * xp.sum(((x - centre) / width) ** 2, axis=-1))

    return Problem("anisotropic peak on a wide box", 3, f, exact, tuple(lo), tuple(hi), True)


def cases() -> list[Problem]:
    """The validation half's new kinds."""
    return [*smooth_high_dimensional(), irradiance(), form_factor(), rotated_gaussian(),
            banana(), coulomb(), singular_circle(), anisotropic_peak()]
