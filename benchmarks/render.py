"""Direct lighting on Veach's MIS scene: every strategy × point set against a reference.

Renders a high-spp reference of `scenes.veach_mis()` (power-heuristic MIS), then
each strategy and point set at equal samples per pixel and at equal time, and
reports each image's mean squared error against the reference. Equal time
averages independent renders of the same compiled size (the number of renders
chosen from the measured steady-state time of one), so no strategy pays for a
recompilation. The reference's own noise is a floor under every MSE; it is
reported alongside.
"""

from __future__ import annotations

import jax
import numpy as np

from jaxmc.render import object_ids, render, save_png, scenes

from ._harness import Context, Result, markdown_table, time_call


TITLE = "Direct lighting: strategies × point sets, MSE against a reference (veach_mis)"

STRATEGIES = ("light", "brdf", "mis_balance", "mis_power", "mis_one_sample")
POINT_SETS = ("uniform", "stratified", "latin_hypercube", "halton")
EXPOSURE = 0.5


# `--quick`: each (strategy, points) pair compiles its own renderer (~5 s), so the quick run
# takes the single strategies, both MIS heuristics with i.i.d. points, and one point set
# driving power-heuristic MIS.
QUICK_COMBOS = (
    ("light", "uniform"),
    ("brdf", "uniform"),
    ("mis_balance", "uniform"),
    ("mis_power", "uniform"),
    ("mis_power", "stratified"),
)


def _combos(quick: bool):
    if quick:
        return list(QUICK_COMBOS)
    return [(s, p) for s in STRATEGIES for p in POINT_SETS]


def _mse(image, ref, mask=None):
    err = (image - ref) ** 2
    return float(np.mean(err if mask is None else err[mask]))


def _reference(key, scene, *, spp, width, height, parts, log):
    """Mean of `parts` independent power-heuristic renders, and a noise estimate of it."""
    images = []
    for i, k in enumerate(jax.random.split(key, parts)):
        part = time_call(
            lambda k=k: render(
                k, scene, strategy="mis_power", spp=spp, width=width, height=height,
                points="uniform",
            ),
            repeats=0,
        )
        images.append(np.asarray(part.output))
        if i < 2 or i + 1 == parts:
            log(f"reference part {i + 1}/{parts}: {part.first_s:.1f} s")
    stack = np.stack(images)
    ref = stack.mean(0)
    # variance of the mean per pixel, averaged: the MSE floor the reference adds
    floor = float(stack.var(0, ddof=1).mean() / parts) if parts > 1 else float("nan")
    return ref, floor


def run(ctx: Context) -> Result:
    quick = ctx.quick
    width, height = (96, 64) if quick else (192, 128)
    spp = 4 if quick else 16
    # quick: the reference renders at the strategies' spp, so it reuses mis_power's compiled
    # renderer instead of compiling one of its own
    ref_spp, ref_parts = (spp, 64) if quick else (256, 8)
    repeats = 8 if quick else 16
    scene = scenes.veach_mis()
    key = jax.random.key(2026)
    k_ref, k_run = jax.random.split(key)

    ctx.log(f"reference: {width}x{height}, {ref_spp * ref_parts} spp (mis_power)")
    ref, floor = _reference(
        k_ref, scene, spp=ref_spp, width=width, height=height, parts=ref_parts, log=ctx.log
    )
    save_png(ctx.out / "render_reference.png", ref, exposure=EXPOSURE)

    combos = _combos(quick)
    timings = {}
    for strategy, points in combos:

        def call(k=k_run, strategy=strategy, points=points):
            return render(
                k, scene, strategy=strategy, spp=spp, width=width, height=height, points=points
            )

        timings[strategy, points] = time_call(call, repeats=5).summary()
        ctx.log(
            f"{strategy:15s} {points:16s} compile+run {timings[strategy, points]['first_s']:.1f} s,"
            f" run {timings[strategy, points]['min_s'] * 1e3:.0f} ms"
        )
    # min over repeats: the least disturbed measurement on a shared machine
    budget = max(t["min_s"] for t in timings.values())
    ids = np.asarray(object_ids(scene, width, height))
    plates = np.isin(ids, [scene.index(f"plate{i}") for i in range(1, 5)])

    data_rows, images = [], {}
    for strategy, points in combos:
        t = timings[strategy, points]["min_s"]
        renders = max(1, round(budget / t))
        draw = lambda k, strategy=strategy, points=points: np.asarray(
            render(k, scene, strategy=strategy, spp=spp, width=width, height=height, points=points)
        )
        # MSE of one image is itself noisy (fireflies): average it over `repeats` images
        errors = []
        for r, k_rep in enumerate(
            jax.random.split(jax.random.fold_in(k_run, len(images)), repeats)
        ):
            shots = [draw(k) for k in jax.random.split(k_rep, renders)]
            if r == 0:
                image = shots[0]
            equal_time = np.mean(shots, axis=0)
            errors.append(
                [
                    _mse(shots[0], ref),
                    _mse(shots[0], ref, plates),
                    _mse(equal_time, ref),
                    _mse(equal_time, ref, plates),
                ]
            )
        images[strategy, points] = image
        mse_spp, mse_plates, mse_time, mse_time_plates = np.mean(errors, axis=0).tolist()
        save_png(ctx.out / f"render_{strategy}_{points}.png", image, exposure=EXPOSURE)
        data_rows.append(
            dict(
                strategy=strategy,
                points=points,
                mse_equal_spp=mse_spp,
                time_s=t,
                equal_time_spp=renders * spp,
                mse_equal_time=mse_time,
                mse_plates_equal_spp=mse_plates,
                mse_plates_equal_time=mse_time_plates,
                compile_s=timings[strategy, points]["first_s"],
            )
        )

    plots = _contact_sheet(ctx, images, ref)
    table = markdown_table(
        [
            "strategy",
            "points",
            f"MSE @ {spp} spp",
            "plates only",
            "time / image (ms)",
            "spp @ equal time",
            "MSE @ equal time",
            "plates only",
        ],
        [
            [
                r["strategy"],
                r["points"],
                r["mse_equal_spp"],
                r["mse_plates_equal_spp"],
                r["time_s"] * 1e3,
                r["equal_time_spp"],
                r["mse_equal_time"],
                r["mse_plates_equal_time"],
            ]
            for r in data_rows
        ],
    )
    markdown = (
        f"{width}×{height} pixels; equal spp = {spp} samples per pixel per technique; "
        f"equal time = the slowest strategy's time for one image ({budget * 1e3:.0f} ms), "
        f"filled by averaging independent renders. Reference: power-heuristic MIS at "
        f"{ref_spp * ref_parts} spp (its own noise adds ≈ {floor:.3g} to every MSE). "
        f"MSE (mean over {repeats} independent images) is over all pixels (RGB) and over the plates' pixels; single bright samples "
        "(a BRDF ray finding a tiny light) dominate it, as fireflies dominate the eye. "
        f"Linear radiance; PNGs at exposure {EXPOSURE} in `render_*.png`.\n\n{table}\n"
    )
    data = dict(
        width=width,
        height=height,
        spp=spp,
        reference_spp=ref_spp * ref_parts,
        reference_noise=floor,
        mse_repeats=repeats,
        budget_s=budget,
        rows=data_rows,
    )
    return Result(markdown=markdown, data=data, plots=plots)


def _contact_sheet(ctx: Context, images, ref) -> list[str]:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        ctx.log("matplotlib missing: no contact sheet")
        return []
    from jaxmc.render import to_srgb8

    panels = [("reference", ref)] + [(f"{s} / {p}", im) for (s, p), im in images.items()]
    cols = 4
    rows = -(-len(panels) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.3 * rows))
    for ax in np.ravel(axes):
        ax.axis("off")
    for ax, (title, im) in zip(np.ravel(axes), panels):
        ax.imshow(to_srgb8(im, EXPOSURE))
        ax.set_title(title, fontsize=8)
    fig.tight_layout()
    name = "render_contact_sheet.png"
    fig.savefig(ctx.out / name, dpi=100)
    plt.close(fig)
    return [name]
