"""Plain Monte Carlo throughput: jaxmc against the raw RNG rate and numpy.

The physical limit of plain MC on a machine is the rate at which the RNG makes
uniforms: `jax.random.uniform` for the same `(n, d)` numbers, reduced to a
sum so nothing is optimised away. jaxmc's `uniform` and `integrate` add the
affine map, the integrand and the moment reductions on top; the target is at
least 0.8 of the raw rate and ahead of a vectorised numpy implementation
(PCG64 via `default_rng`, float32) at every d, in samples/s, steady state.
Compile time is reported separately. Every JAX path is timed with keys of the
default threefry implementation and of `rbg` (XLA's RngBitGenerator; not in
`--quick` runs, whose time goes to compiles, two per path and key kind). jaxmc
draws its uniforms with its own Threefry-2x32-20 written in `jnp`, which
XLA fuses and vectorises; the key only seeds it, so the raw column measures
`jax.random`, not jaxmc's generator.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import jaxmc

from ._harness import Context, Result, markdown_table, time_call


TITLE = "Plain MC throughput: jaxmc vs the raw RNG rate and numpy"


def _integrand(x):
    # Cheap and not separable into the RNG: a sum of squares.
    return jnp.sum(x * x)


def _numpy_plain(rng: np.random.Generator, n: int, d: int, chunk: int) -> tuple[float, float]:
    """Vectorised numpy plain MC of the same integrand on [0,1]^d, float32, chunked."""
    total = 0.0
    total_sq = 0.0
    done = 0
    while done < n:
        m = min(chunk, n - done)
        x = rng.random((m, d), dtype=np.float32)
        y = np.einsum("ij,ij->i", x, x)
        total += float(y.sum(dtype=np.float64))
        total_sq += float((y.astype(np.float64) ** 2).sum())
        done += m
    mean = total / n
    return mean, (total_sq / n - mean**2) / n


def run(ctx: Context) -> Result:
    dims = (1, 4, 16)
    repeats = 3 if ctx.quick else 7
    impls = ("threefry2x32",) if ctx.quick else ("threefry2x32", "rbg")
    rows, data = [], []
    for d in dims:
        n = (1 << 20 if ctx.quick else 1 << 24) if d < 16 else (1 << 18 if ctx.quick else 1 << 22)
        lo, hi = jnp.zeros(d, jnp.float32), jnp.ones(d, jnp.float32)
        entry = {"d": d, "n": n}
        for impl in impls:
            key = jax.random.key(0, impl=impl)
            raw = jax.jit(lambda k: jnp.sum(jax.random.uniform(k, (n, d), jnp.float32)))
            uni = jax.jit(lambda k: jaxmc.uniform(k, _integrand, lo, hi, n))
            timings = {
                "raw": time_call(lambda: raw(key), repeats=repeats).summary(),
                "uniform": time_call(lambda: uni(key), repeats=repeats).summary(),
                "integrate": time_call(
                    lambda: jaxmc.integrate(key, _integrand, lo, hi, n=n, method="plain"),
                    repeats=repeats,
                ).summary(),
            }
            entry[impl] = {
                name: {**t, "samples_per_s": n / t["median_s"]} for name, t in timings.items()
            }
            ctx.log(
                f"d={d} {impl}: "
                + ", ".join(f"{k} {n / t['median_s'] / 1e6:.1f} M/s" for k, t in timings.items())
            )
        rng = np.random.default_rng(0)
        t_np = time_call(lambda: _numpy_plain(rng, n, d, 1 << 20), repeats=repeats).summary()
        entry["numpy"] = {**t_np, "samples_per_s": n / t_np["median_s"]}
        ctx.log(f"d={d} numpy: {n / t_np['median_s'] / 1e6:.1f} M/s")
        data.append(entry)
        for impl in impls:
            e = entry[impl]
            raw_rate = e["raw"]["samples_per_s"]
            for name in ("uniform", "integrate"):
                rate = e[name]["samples_per_s"]
                rows.append(
                    [
                        d,
                        impl,
                        f"jaxmc.{name}",
                        rate / 1e6,
                        raw_rate / 1e6,
                        rate / raw_rate,
                        entry["numpy"]["samples_per_s"] / 1e6,
                        rate / entry["numpy"]["samples_per_s"],
                        e[name]["first_s"],
                    ]
                )
    header = [
        "d",
        "JAX RNG",
        "path",
        "Msamples/s",
        "raw RNG Msamples/s",
        "ratio to raw (target >= 0.8)",
        "numpy Msamples/s",
        "ratio to numpy (target > 1)",
        "first call s (compile)",
    ]
    markdown = (
        "Steady-state medians; one sample is one d-dimensional point and one "
        "integrand evaluation. The raw rate is `jax.random.uniform`'s; jaxmc draws "
        "its uniforms with its own fused Threefry, seeded by the key.\n\n"
        + markdown_table(header, rows)
    )
    return Result(markdown=markdown, data={"results": data})
