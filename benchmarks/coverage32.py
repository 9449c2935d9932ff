r"""Coverage in float32: `integrate` with its defaults, in JAX's default precision.

float32 resolves about 7 digits: an integrand's own rounding, the map's and the
accumulation's can exceed an error bar that the samples' spread puts at $10^{-7}$ of
the mean. For each case, `KEYS` runs of `jaxmc.integrate(key, f, lo, hi, n=N)` on float32
bounds; each gives $z = (\hat I - I)/\widehat{\mathrm{se}}$ (as the normal $|z|$ of the same
tail probability, given the error bar's degrees of freedom), and whether
`jaxmc.stats.unreliable` flags the run. A case *passes* when its 2σ coverage is at least
0.85 or its misses are flagged, and no run beyond 5σ is unflagged. The exact integrals are
closed forms, evaluated in float64.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

import jaxmc

from ._harness import Context, Result, markdown_table, normal_equivalent


TITLE = "Coverage of the error bars in float32"

KEYS = 32
MIN_COVERAGE = 0.85
MAX_UNFLAGGED_Z = 5.0


@dataclasses.dataclass(frozen=True)
class Case:
    name: str
    f: Callable
    lo: tuple[float, ...]
    hi: tuple[float, ...]
    exact: float
    n: int


def _breit_wigner(width: float, n: int) -> Case:
    """A Z resonance in s = m^2 (M = 91.19, the given width) times a smooth angular and
    momentum-fraction factor, on [60^2, 120^2] x [-0.8, 1] x [0, 2 pi] x [0.01, 1]."""
    m = 91.19

    def f(x):
        s, c, phi, t = x[0], x[1], x[2], x[3]
        return (1 + c**2) * (2 + jnp.cos(phi)) * t / ((s - m**2) ** 2 + (m * width) ** 2)

    lo, hi = (60.0**2, -0.8, 0.0, 0.01), (120.0**2, 1.0, 2 * math.pi, 1.0)
    resonance = (math.atan((hi[0] - m**2) / (m * width))
                 - math.atan((lo[0] - m**2) / (m * width))) / (m * width)
    angular = (1.8 + (1 + 0.8**3) / 3) * (4 * math.pi)
    return Case(f"Breit-Wigner 4-D (width {width:g}), n={n:.0e}", f, lo, hi,
                resonance * angular * (1 - 0.01**2) / 2, n)


def cases() -> list[Case]:
    def peak(x):
        return jnp.exp(-jnp.sum((x - 0.4) ** 2) / (2 * 0.05**2))

    def corner(x):
        return jnp.prod(x ** -0.5)

    def smooth(x):
        return jnp.exp(-jnp.sum(x**2))

    def wave(x):
        return jnp.cos(jnp.sum(x))

    gauss_1d = math.sqrt(math.pi) / 2 * math.erf(1.0)
    peak_1d = 0.05 * math.sqrt(2 * math.pi) * 0.5 * (math.erf(0.6 / (0.05 * math.sqrt(2)))
                                                     + math.erf(0.4 / (0.05 * math.sqrt(2))))
    return [
        _breit_wigner(0.05, 10**6),
        _breit_wigner(2.5, 10**6),
        Case("Gaussian peak 4-D (sd 0.05), n=1e+05", peak, (0.0,) * 4, (1.0,) * 4,
             peak_1d**4, 10**5),
        Case("x^-1/2 product 2-D, n=1e+05", corner, (0.0,) * 2, (1.0,) * 2, 4.0, 10**5),
        Case("exp(-|x|^2) 4-D, n=1e+06", smooth, (0.0,) * 4, (1.0,) * 4, gauss_1d**4, 10**6),
        Case("cos(x_1 + ... + x_8) 8-D, n=1e+05", wave, (0.0,) * 8, (1.0,) * 8,
             float(np.real(((np.exp(1j) - 1) / 1j) ** 8)), 10**5),
    ]


def measure(ctx: Context, case: Case, keys: int = KEYS) -> dict:
    """One case's runs, in float32 (call it with x64 off: the bounds set the dtype)."""
    lo, hi = jnp.asarray(case.lo, jnp.float32), jnp.asarray(case.hi, jnp.float32)
    zs, flags, methods = [], [], []
    for k in range(keys):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", jaxmc.ReliabilityWarning)
            est = jaxmc.integrate(jax.random.key(k), case.f, lo, hi, n=case.n)
        assert est.mean.dtype == jnp.float32
        z = abs(float(est.mean) - case.exact) / float(est.stderr)
        zs.append(float(normal_equivalent(z, float(est.dof))))
        flags.append(bool(jaxmc.stats.unreliable(est)))
        methods.append(est.method)
    zs, flags = np.array(zs), np.array(flags)
    missed = zs > 2
    coverage = float(np.mean(~missed))
    unflagged = zs[~flags]
    entry = {
        "case": case.name, "keys": keys, "coverage_2sigma": coverage,
        "rms_z": float(np.sqrt(np.mean(np.minimum(zs, 1e6) ** 2))),
        "flagged": float(np.mean(flags)), "misses_flagged": bool(np.all(flags[missed])),
        "max_unflagged_z": float(unflagged.max()) if unflagged.size else 0.0,
        "methods": {m: methods.count(m) for m in sorted(set(methods))},
    }
    entry["passes"] = bool((coverage >= MIN_COVERAGE or entry["misses_flagged"])
                           and entry["max_unflagged_z"] <= MAX_UNFLAGGED_Z)
    ctx.log(f"{case.name}: coverage {coverage:.2f}, rms z {entry['rms_z']:.2f}, flagged "
            f"{entry['flagged']:.2f}, max unflagged |z| {entry['max_unflagged_z']:.1f}, "
            f"{'pass' if entry['passes'] else 'FAIL'}")
    return entry


def run(ctx: Context) -> Result:
    with jax.enable_x64(False):
        entries = [measure(ctx, case) for case in cases()]
    header = ["case", "2σ coverage", "rms z", "flagged", "misses all flagged",
              "max unflagged |z|", "methods", "passes"]
    rows = [[e["case"], e["coverage_2sigma"], e["rms_z"], e["flagged"],
             "yes" if e["misses_flagged"] else "no", e["max_unflagged_z"],
             ", ".join(f"{m} {c}" for m, c in e["methods"].items()),
             "yes" if e["passes"] else "no"] for e in entries]
    passed = sum(e["passes"] for e in entries)
    markdown = (
        f"`integrate(key, f, lo, hi, n=N)` with float32 bounds, {KEYS} keys per case; |z| as "
        f"the normal |z| of the same tail probability given the error bar's degrees of "
        f"freedom. A case passes when its 2σ coverage is at least {MIN_COVERAGE} or its "
        f"misses are flagged by `jaxmc.stats.unreliable`, and no unflagged run is beyond "
        f"{MAX_UNFLAGGED_Z:g}σ: {passed} of {len(entries)} pass.\n\n"
        + markdown_table(header, rows) + "\n"
    )
    return Result(markdown=markdown, data={"cases": entries})
