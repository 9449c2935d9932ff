"""Plans reused over a family of integrals, and a long session of new integrands.

**Plans.** A family $f(x; a)$ is integrated once with `method="auto"` at $a_0$; its plan,
`est.plan`, then integrates 8 members at once, `jax.jit(jax.vmap(...))` over `args`, and
the same 8 by a loop of one `jax.jit` call each. Reported: both steady-state times
(medians over repeats) and their ratio (target: the batch at most 1.2 times the loop),
the programs the batch's first call compiled, and whether a pilot ran (it must not:
`pilot` is None on every member). The same batch without a plan (`auto` under `vmap`,
whose pilot pools the batch's figures into one choice) is timed beside it.

**Session.** One process integrates `SESSION` different integrands (Gaussian peaks,
plane waves, ridges, in 2-6 dimensions) with the default method at $10^5$ evaluations,
without `jax.clear_caches()`: the first-call time of each, and the process's memory
mappings (Linux's `/proc/self/maps`; the kernel's limit, `vm.max_map_count`, is 65,530
by default) as the integrands go by. Each estimate is checked against its closed form.

The suite has no quick setting (its point is a long session): `--quick` skips it.
"""

from __future__ import annotations

import math
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxmc

from ._harness import (
    Context,
    Result,
    compiled_programs,
    markdown_table,
    normal_equivalent,
    time_call,
)


TITLE = "Plans reused over a family of integrals; a long session of new integrands"

BATCH = 8
SESSION = 150
REPEATS = 7
BUDGET = 100_000
MAPS = Path("/proc/self/maps")


def _families():
    """`(name, d, f(x, a), exact(a), a_0, a batch of a)`: a peak the grid wins on, a smooth
    integrand QMC wins on."""
    def peak(x, a):  # a Gaussian of width 0.05 at `a` on the diagonal, in 4-D
        return jnp.exp(-jnp.sum((x - a) ** 2) / (2 * 0.05**2))

    def peak_exact(a):
        return float(np.sqrt(2 * np.pi) * 0.05) ** 4  # (well inside the cube)

    def wave(x, a):  # cos(a + sum x), in 8-D
        return jnp.cos(a + jnp.sum(x))

    def wave_exact(a):  # Re e^{ia} prod (e^{i} - 1)/i
        return float(np.real(np.exp(1j * a) * ((np.exp(1j) - 1) / 1j) ** 8))

    return [
        ("Gaussian peak, 4-D", 4, peak, peak_exact, 0.45, np.linspace(0.4, 0.6, BATCH)),
        ("plane wave, 8-D", 8, wave, wave_exact, 0.3, np.linspace(0.1, 1.0, BATCH)),
    ]


def _plans(ctx: Context) -> tuple[list[list], list[dict]]:
    repeats = REPEATS
    rows, data = [], []
    for name, d, f, exact, a0, batch in _families():
        lo, hi = jnp.zeros(d), jnp.ones(d)
        first = jaxmc.integrate(jax.random.key(0), f, lo, hi, n=BUDGET, args=a0)
        plan = first.plan
        keys = jax.random.split(jax.random.key(1), BATCH)
        a = jnp.asarray(batch)

        def one(k, a, method=plan):
            return jaxmc.integrate(k, f, lo, hi, n=BUDGET, args=a, method=method)

        batched = jax.jit(jax.vmap(one))
        single = jax.jit(one)
        with compiled_programs() as compiled:
            runs = jax.block_until_ready(batched(keys, a))
        t_batch = time_call(lambda: batched(keys, a), repeats=repeats)
        t_loop = time_call(lambda: [single(keys[i], a[i]) for i in range(BATCH)],
                           repeats=repeats)
        pooled = jax.jit(jax.vmap(lambda k, a: one(k, a, "auto")))
        t_pooled = time_call(lambda: pooled(keys, a), repeats=max(1, repeats // 2))
        auto_single = jax.jit(lambda k, a: one(k, a, "auto"))
        t_auto_loop = time_call(lambda: [auto_single(keys[i], a[i]) for i in range(BATCH)],
                                repeats=max(1, repeats // 2))
        truth = np.array([exact(float(v)) for v in batch])
        z = normal_equivalent(np.abs(np.asarray(runs.mean) - truth) / np.asarray(runs.stderr),
                              np.broadcast_to(np.asarray(runs.dof, float), truth.shape))
        entry = {
            "family": name, "d": d, "plan": first.method, "n": BUDGET,
            "batch_s": t_batch.summary(), "loop_s": t_loop.summary(),
            "ratio": t_batch.median_s / t_loop.median_s,
            "programs_compiled": len(compiled), "compile_s": sum(compiled),
            "pilot_ran": runs.pilot is not None, "max_abs_z": float(z.max()),
            "auto_batch_s": t_pooled.summary(), "auto_loop_s": t_auto_loop.summary(),
        }
        ctx.log(f"{name}: plan {first.method}, batch {t_batch.median_s * 1e3:.1f} ms, loop "
                f"{t_loop.median_s * 1e3:.1f} ms, ratio {entry['ratio']:.2f}; "
                f"{len(compiled)} programs; max |z| {entry['max_abs_z']:.2f}")
        data.append(entry)
        rows.append([name, first.method, t_batch.median_s * 1e3, t_loop.median_s * 1e3,
                     entry["ratio"], len(compiled), t_batch.first_s,
                     "yes" if entry["pilot_ran"] else "no", entry["max_abs_z"],
                     t_pooled.median_s * 1e3, t_auto_loop.median_s * 1e3])
    return rows, data


def _mappings() -> int | None:
    try:
        return sum(1 for _ in MAPS.open())
    except OSError:  # (not Linux)
        return None


def _session_integrand(i: int, rng: np.random.Generator):
    """The `i`-th integrand of the session and its integral over the unit cube."""
    d = 2 + i % 5
    kind = i % 3
    if kind == 0:  # a Gaussian peak well inside the cube
        c, w = rng.uniform(0.35, 0.65), rng.uniform(0.04, 0.1)
        return d, (lambda x: jnp.exp(-jnp.sum((x - c) ** 2) / (2 * w**2))), \
            (math.sqrt(2 * math.pi) * w) ** d
    if kind == 1:  # a plane wave
        c = rng.uniform(0, 2 * math.pi)
        return d, (lambda x: jnp.cos(c + jnp.sum(x))), \
            float(np.real(np.exp(1j * c) * ((np.exp(1j) - 1) / 1j) ** d))
    k = rng.uniform(1, 3)  # exp(-k (x_1 + ... + x_d))
    return d, (lambda x: jnp.exp(-k * jnp.sum(x))), ((1 - math.exp(-k)) / k) ** d


def _session(ctx: Context) -> dict:
    count = SESSION
    rng = np.random.default_rng(0)
    firsts, maps, zs = [], [], []
    start = time.perf_counter()
    for i in range(count):
        d, f, exact = _session_integrand(i, rng)
        t = time.perf_counter()
        est = jax.block_until_ready(jaxmc.integrate(jax.random.key(i), f, jnp.zeros(d),
                                                    jnp.ones(d), n=BUDGET))
        firsts.append(time.perf_counter() - t)
        zs.append(normal_equivalent(abs(float(est.mean) - exact) / float(est.stderr),
                                    float(est.dof)))
        maps.append(_mappings())
        if i % 10 == 9:
            ctx.log(f"session: {i + 1} integrands, mappings {maps[-1]}, "
                    f"{time.perf_counter() - start:.0f} s")
    known = [m for m in maps if m is not None]
    return {
        "integrands": count, "n": BUDGET, "first_call_median_s": statistics.median(firsts),
        "first_call_max_s": max(firsts), "total_s": time.perf_counter() - start,
        "mappings": maps, "max_mappings": max(known) if known else None,
        "max_abs_z": float(np.max(zs)), "coverage_2sigma": float(np.mean(np.array(zs) <= 2)),
    }


def run(ctx: Context) -> Result:
    with jax.enable_x64(True):
        rows, plans = _plans(ctx)
        session = _session(ctx)
    header = ["family", "plan", "batch ms", "loop ms", "batch / loop (target <= 1.2)",
              "programs (batch's 1st call)", "batch 1st call s", "pilot ran",
              "max |z| of 8", "auto batch ms (no plan)", "auto loop ms (no plan)"]
    maps = session["mappings"]
    trend = ("mappings not measured (no /proc/self/maps)" if session["max_mappings"] is None
             else f"memory mappings after 10, half and all integrands: {maps[min(9, len(maps) - 1)]}, "
                  f"{maps[len(maps) // 2]}, {maps[-1]} (max {session['max_mappings']})")
    markdown = (
        f"Plans: {BATCH} members of each family at n = {BUDGET:.0e}, float64; steady-state "
        "medians; `max |z|`: the largest |estimate − exact| / stderr of the batch, as the "
        "normal |z| with the same tail probability given the error bar's degrees of freedom.\n\n"
        + markdown_table(header, rows)
        + f"\n\nSession: {session['integrands']} different integrands, `auto` at n = "
          f"{BUDGET:.0e}, one process, no `jax.clear_caches()`: first call median "
          f"{session['first_call_median_s']:.2f} s (max {session['first_call_max_s']:.1f} s), "
          f"{session['total_s']:.0f} s in all; {trend}; max |z| {session['max_abs_z']:.2f}, 2σ coverage "
          f"{session['coverage_2sigma']:.2f}.\n"
    )
    return Result(markdown=markdown, data={"plans": plans, "session": session})
