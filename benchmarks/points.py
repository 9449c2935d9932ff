"""Point sets against SciPy: steady-state points per second of every `jaxmc.points` generator.

Each jaxmc call is jitted and timed with `time_call` (first call = compile + run,
reported apart; then the median of repeats). Each competitor call builds its
SciPy engine and draws `n` points, as a user would. SciPy has no rank-1 lattice
and no jittered grid, so those are compared with the obvious NumPy code.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxmc import points

from ._harness import Context, Result, markdown_table, optional_import, time_call


TITLE = "Point sets against SciPy (samples/s)"


def _stratified_counts(n: int, d: int) -> tuple[int, ...] | None:
    """Strata per axis with `prod == n` (n a power of two), as even as possible."""
    m = n.bit_length() - 1
    if 2**m != n:
        return None
    per_axis = [m // d + (1 if j < m % d else 0) for j in range(d)]
    return tuple(2**k for k in per_axis)


def _lattice_vector(n: int, d: int) -> np.ndarray:
    """jaxmc's generating vector modulo `n` (a power of two): point 1 of its lattice is z/n."""
    return np.rint(np.asarray(points.lattice(n, d)[1], np.float64) * n).astype(np.int64)


def _numpy_lattice(n: int, d: int, z: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    x = (np.arange(n, dtype=np.int64)[:, None] * z[None, :] % n) / n
    return (x + rng.random(d)) % 1.0


def _numpy_stratified(counts: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
    c = np.asarray(counts)
    strides = np.concatenate([np.cumprod(c[::-1])[::-1][1:], [1]])
    i = np.arange(int(np.prod(c)))[:, None]
    cells = (i // strides) % c
    return (cells + rng.random(cells.shape)) / c


def _counts_label(counts: tuple[int, ...]) -> str:
    runs: list[list[int]] = []
    for c in counts:
        if runs and runs[-1][0] == c:
            runs[-1][1] += 1
        else:
            runs.append([c, 1])
    return "·".join(f"{c}^{k}" if k > 1 else str(c) for c, k in runs)


def _cases(
    n: int, d: int, qmc: Any
) -> list[tuple[str, Callable[[], Any], str, Callable[[], Any] | None]]:
    key = jax.random.key(0)
    rng = np.random.default_rng(0)
    jit = jax.jit
    cases: list[tuple[str, Callable[[], Any], str, Callable[[], Any] | None]] = []

    def scipy_or_none(make: Callable[[], Any]) -> Callable[[], Any] | None:
        return make if qmc is not None else None

    sobol_plain = jit(lambda: points.sobol(n, d))
    sobol_key = jit(lambda k: points.sobol(n, d, key=k))
    halton_plain = jit(lambda: points.halton(n, d))
    halton_key = jit(lambda k: points.halton(n, d, key=k))
    lattice_key = jit(lambda k: points.lattice(n, d, key=k))
    lhs = jit(lambda k: points.latin_hypercube(k, n, d))
    uniform = jit(lambda k: points.uniform(k, n, d))
    cases += [
        (
            "sobol",
            sobol_plain,
            "qmc.Sobol(scramble=False)",
            scipy_or_none(lambda: qmc.Sobol(d, scramble=False).random(n)),
        ),
        (
            "sobol (LMS+shift)",
            lambda: sobol_key(key),
            "qmc.Sobol(scramble=True)",
            scipy_or_none(lambda: qmc.Sobol(d, rng=rng).random(n)),
        ),
        (
            "halton",
            halton_plain,
            "qmc.Halton(scramble=False)",
            scipy_or_none(lambda: qmc.Halton(d, scramble=False).random(n)),
        ),
        (
            "halton (permuted)",
            lambda: halton_key(key),
            "qmc.Halton(scramble=True)",
            scipy_or_none(lambda: qmc.Halton(d, rng=rng).random(n)),
        ),
    ]
    if d <= points.LATTICE_MAX_DIM:
        z = _lattice_vector(n, d)
        cases.append(
            (
                "lattice (shifted)",
                lambda: lattice_key(key),
                "numpy lattice",
                lambda: _numpy_lattice(n, d, z, rng),
            )
        )
    cases.append(
        (
            "latin_hypercube",
            lambda: lhs(key),
            "qmc.LatinHypercube",
            scipy_or_none(lambda: qmc.LatinHypercube(d, rng=rng).random(n)),
        )
    )
    counts = _stratified_counts(n, d)
    if counts is not None:
        strat = jit(lambda k: points.stratified(k, counts))
        label = _counts_label(counts)
        cases.append(
            (
                f"stratified ({label})",
                lambda: strat(key),
                "numpy jittered grid",
                lambda: _numpy_stratified(counts, rng),
            )
        )
    cases.append(
        ("uniform", lambda: uniform(key), "numpy Generator.random", lambda: rng.random((n, d)))
    )
    return cases


def run(ctx: Context) -> Result:
    qmc = optional_import("scipy.stats.qmc")
    n = 2**18 if ctx.quick else 2**20
    repeats = 2 if ctx.quick else 5
    dims = (8,) if ctx.quick else (8, 64)  # quick: compiles dominate, and grow with d
    dtype = jnp.dtype(jnp.result_type(float)).name
    rows: list[list[Any]] = []
    data: dict[str, Any] = {"n": n, "dims": list(dims), "dtype": dtype, "cases": []}
    missed = []
    for d in dims:
        for name, ours, their_name, theirs in _cases(n, d, qmc):
            ctx.log(f"d={d} {name}")
            ours_t = time_call(ours, repeats=repeats).summary()
            entry = {"d": d, "jaxmc": name, "jaxmc_time": ours_t, "competitor": their_name}
            if theirs is None:
                rows.append(
                    [
                        d,
                        name,
                        n / ours_t["median_s"] / 1e6,
                        ours_t["first_s"],
                        their_name,
                        "missing",
                        "-",
                        "-",
                    ]
                )
                entry["competitor_time"] = None
            else:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    their_t = time_call(theirs, repeats=max(1, repeats - 1)).summary()
                speedup = their_t["median_s"] / ours_t["median_s"]
                faster = speedup > 1
                if not faster:
                    missed.append(f"{name} (d={d})")
                rows.append(
                    [
                        d,
                        name,
                        n / ours_t["median_s"] / 1e6,
                        ours_t["first_s"],
                        their_name,
                        n / their_t["median_s"] / 1e6,
                        speedup,
                        "yes" if faster else "**no**",
                    ]
                )
                entry.update(competitor_time=their_t, speedup=speedup)
            data["cases"].append(entry)
    header = [
        "d",
        "jaxmc",
        "Mpoints/s",
        "first call s",
        "competitor",
        "Mpoints/s",
        "speed-up",
        "faster?",
    ]
    notes = [
        f"n = {n:,} points of dimension d per call; jaxmc returns {dtype} "
        f"({'x64 enabled' if dtype == 'float64' else 'JAX default'}), SciPy/NumPy float64. "
        "Speed-up = competitor median time / jaxmc median time (steady state, compile excluded; "
        "the first call, compile included, is listed apart).",
        f"JAX {jax.__version__} on {jax.device_count()} {jax.default_backend()} device(s). "
        "Timings on a shared 2-core machine are noisy; compare ratios, not absolute rates.",
    ]
    if missed:
        notes.append("Target missed (jaxmc not faster): " + ", ".join(missed) + ".")
    data["missed"] = missed
    markdown = markdown_table(header, rows) + "\n\n" + "\n".join(f"- {s}" for s in notes) + "\n"
    return Result(markdown=markdown, data=data)
