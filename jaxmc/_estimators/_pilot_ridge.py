r"""The ridge density (`_ridge`) as a candidate of `integrate(method="auto")`'s pilot.

Sought where QMC won no clear win and its cost is at least `RIDGE_MIN_COST`, after
QMC's early look and outside `jit` only (`ridge_probe`), and only where $f$'s gradients at
the early look's largest values are parallel and $f$ keeps its value a step across them
(`ridge_direction`, 32 evaluations). Where the pilot's winner costs as much, the profile
$|g|$ is read along the cube's diagonal (`profiled_ridge`) and QMC through it measured as
QMC through the grid is (`with_ridge_candidate`): chosen where it costs less (its stage
is paid by then; on the 12-D resonance at 1e6, key 0, a margin of 2 had kept QMC, at 8x the
error of the keys that took the ridge).

The `auto` suite's oblique resonances (width 0.01; 40 keys, RMS relative error, QMC alone
before): 4-D 1.2e-2 -> 9.5e-4 at 1e5 and 2.6e-3 -> 1.2e-3 at 1e6, 12-D 1.6e-2 -> 2.5e-3 and
5.7e-3 -> 2.0e-3. At 1e6 the keys that kept QMC erred 1.4e-3 to 1.2e-2 (the 4-D's worst three:
QMC's early figure read 0.03-0.15, below `RIDGE_MIN_COST`, plain MC's on the same points ~10;
the 12-D's worst: the ridge's figure read 2.0 against QMC's 0.58); without the worst three of
each, 1.0e-4 and 4.8e-4.
"""
from __future__ import annotations

import jax

from ._pilot_grid import grid_qmc_pilot
from ._pilot_nets import MAX_NET_GROWTH, net_points
from ._pilot_record import appended, charged_to_qmc
from ._plan import final_net
from ._ridge import (
    PROBE_EVALUATIONS,
    RIDGE_MIN_COST,
    profiled_ridge,
    ridge_direction,
    ridge_evaluations,
    ridge_table_size,
    room_for_a_ridge,
)


__all__ = ["RIDGE_COST", "RIDGE_MIN_COST", "ridge_probe", "room_for_a_ridge",
           "with_ridge_candidate"]

# Time per evaluation relative to a Sobol' point's, as QMC through a grid (`_auto.RELATIVE_COST`).
RIDGE_COST = 2.0


def ridge_probe(key, f, lo, hi, early, *, batched, per_replica):
    """`ridge_direction` at QMC's early look (`key` its key, `early` its values): `(evaluations
    spent, (w, its largest component's axis) or None)`. Nothing is spent in one dimension or
    where JAX cannot differentiate $f$."""
    if lo.ndim == 0 or lo.shape[0] < 2:
        return 0, None
    log2_size = (per_replica // 4).bit_length() - 1
    # (The early look's points, made anew in the probe's own program.)
    points = jax.tree_util.Partial(net_points, key, lo, hi, 0, 1, log2_size)
    try:
        direction, ridge, axis = ridge_direction(f, batched, lo, hi, points, early)
    except Exception:  # noqa: BLE001 (any failure to differentiate means: no ridge)
        return 0, None
    ridge, axis = jax.device_get((ridge, axis))  # (one read)
    return PROBE_EVALUATIONS, ((direction, int(axis)) if ridge else None)


def with_ridge_candidate(result, key, f, lo, hi, probe, *, batched, budget, per_replica):
    """The pilot's `result` (`run_pilot`'s) with the ridge among its candidates (`probe`,
    `ridge_probe`'s). Where it found a ridge and the winner costs at least `RIDGE_MIN_COST`
    (Genz's corner peak is a ridge function that QMC through the grid flattens), QMC's nets
    through `profiled_ridge` are measured as QMC through a grid is (`grid_qmc_pilot`, its
    variance `inf` where $f/q$ fits loosely or has a power-law tail) and chosen where they
    cost less. Its evaluations are taken from the stream's; where it was not measured it is no
    candidate, and the probes count in QMC's evaluations."""
    pilot, state, mixture, rest = result
    spent, found = probe
    figures = ridge = None
    if found is not None and bool(room_for_a_ridge(pilot.cost[pilot.choice])):
        quarter = per_replica // 4
        spent += ridge_evaluations(budget, quarter)
        ridge = profiled_ridge(lo, hi, *found, f=f, batched=batched,
                               steps=ridge_table_size(budget))
        growth = min(final_net(rest - spent) / quarter, MAX_NET_GROWTH)
        figures = grid_qmc_pilot(jax.random.fold_in(key, 1), ridge, f=f, per_replica=quarter,
                                 growth=growth, batched=batched)
    if figures is None:  # (the probes were at QMC's points: they count in its evaluations)
        return charged_to_qmc(pilot, spent), state, mixture, rest - spent
    pilot = appended(pilot, "ridge_qmc", figures.variance, figures.blind, RIDGE_COST, spent)
    if int(pilot.choice) == len(pilot.candidates) - 1:
        return pilot, ridge, None, rest - spent  # (the map "ridge_qmc" streams through)
    return pilot, state, mixture, rest - spent

