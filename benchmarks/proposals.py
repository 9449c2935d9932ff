"""Sampling a proposal: jaxmc against SciPy.

The rate of a draw with its density (`sample(key, n)`: the points and $p(x)$)
of a `GaussianMixture` of 8 truncated Gaussians, a `Grid` and `auto`'s
defensive `Mixture` of the two (9 : 1), the proposals passed to the compiled
function as arguments, as `fit` and `auto`'s pilot pass them (a proposal
closed over is folded into constants, which hides what its per-component
arithmetic costs). The anchor is the same Gaussian mixture drawn with NumPy and
`scipy.stats.truncnorm` (inverse CDF). Float64 throughout.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxmc.proposals import GaussianMixture, Grid, Mixture

from ._harness import Context, Result, markdown_table, time_call


TITLE = "Sampling a proposal against SciPy"
COMPONENTS = 8


def _proposals(d: int):
    """A mixture of narrow Gaussians at random places, a grid, and the two mixed as auto mixes them."""
    lo, hi = jnp.zeros(d), jnp.ones(d)
    gm = GaussianMixture(jax.random.key(d), lo, hi, COMPONENTS, scale=0.05)
    grid = Grid(lo, hi, bins=256)
    return gm, grid, Mixture((gm, grid), (0.9, 0.1))


def _scipy_sample(rng, gm: GaussianMixture, n: int):
    """The same truncated Gaussian mixture drawn with NumPy and SciPy: `(x, p(x))`."""
    from scipy import stats

    means, scales = np.asarray(gm.means), np.exp(np.asarray(gm.log_scales))
    weights = np.asarray(jax.nn.softmax(gm.logits))
    a, b = (0 - means) / scales, (1 - means) / scales
    k = rng.choice(COMPONENTS, size=n, p=weights)
    x = stats.truncnorm.ppf(rng.random((n, means.shape[1])), a[k], b[k], means[k], scales[k])
    density = stats.truncnorm.pdf(x[:, None, :], a, b, means, scales)  # (n, K, d)
    return x, np.prod(density, axis=-1) @ weights


def _rate(timing, n: int) -> dict:
    return {**timing.summary(), "points_per_s": n / timing.median_s}


def run(ctx: Context) -> Result:
    with jax.enable_x64(True):
        return _run(ctx)


def _run(ctx: Context) -> Result:
    dims = (2, 8) if ctx.quick else (2, 4, 8, 16)
    repeats = 3 if ctx.quick else 7
    n = 1 << (16 if ctx.quick else 18)
    sample = eqx.filter_jit(lambda proposal, key: proposal.sample(key, n))
    rows, data = [], []
    for d in dims:
        gm, grid, mixture = _proposals(d)
        rates = {}
        for name, proposal in (("GaussianMixture", gm), ("Grid", grid), ("Mixture", mixture)):
            keys = iter(jax.random.split(jax.random.key(0), repeats + 1))
            timing = time_call(lambda p=proposal, ks=keys: sample(p, next(ks)), repeats=repeats)
            rates[name] = _rate(timing, n)
        rng = np.random.default_rng(0)
        rates["scipy"] = _rate(time_call(lambda: _scipy_sample(rng, gm, n), repeats=repeats), n)
        for name in ("GaussianMixture", "Grid", "Mixture"):
            rate = rates[name]["points_per_s"]
            rows.append([d, name, rate / 1e6, rate / rates["scipy"]["points_per_s"],
                         rates[name]["first_s"]])
        ctx.log(f"d={d}: " + ", ".join(f"{k} {v['points_per_s'] / 1e6:.2f} M/s" for k, v in rates.items()))
        data.append({"d": d, "sampling": rates})
    markdown = (
        f"Draws of {n:,} points with their density, steady-state medians; SciPy draws the same "
        "Gaussian mixture (`scipy.stats.truncnorm`, inverse CDF).\n\n"
        + markdown_table(["d", "proposal", "Mpoints/s", "ratio to SciPy's Gaussian mixture", "first call s (compile)"],
                         rows)
    )
    return Result(markdown=markdown, data={"results": data})
