r"""The map bent towards a singular corner (`_corner`) as a candidate of `integrate(method="auto")`'s
pilot.

Sought where QMC's values (its early look's or its whole nets') or the grid's rounds show a
power-law tail (an unbounded integrand), outside `jit` only: `corner_probe` reads $f$ along
rays to the corner that QMC's largest early values lie nearest, by a vote.
Where it finds a power law, QMC's nets through the `CornerMap` are measured as QMC through
a bent grid is (`grid_qmc_pilot`: values that reach a cap are no tail, since $f/q$ is
bounded by construction) and chosen where they cost less than the pilot's winner. The map
streams as a bent grid does, with at least `BENT_REPLICAS` replicas.
"""
from __future__ import annotations

import jax

from ._corner import bends_corner, corner_probe, corner_probe_evaluations
from ._edged_grid import BENT_REPLICAS, edge_powers
from ._pilot_grid import grid_qmc_pilot
from ._pilot_nets import MAX_NET_GROWTH, net_points
from ._pilot_record import appended, charged_to_qmc, dropped
from ._plan import QMC_REPLICAS, final_net


__all__ = ["CORNER_COST", "seek_corner", "with_corner_candidate"]

# Time per evaluation relative to a Sobol' point's (`_auto.RELATIVE_COST`): a logarithm and an
# exponential per coordinate. Measured on 8 nets of 2^16 points and a cheap integrand: 2.9x a
# bare Sobol' point in 4-D and 8-D, 6.5x in 16-D (QMC through a 256-bin grid: 2.3-2.5x, 4.1x).
CORNER_COST = 3.0


def seek_corner(key, f, lo, hi, early, *, batched, per_replica):
    """`corner_probe` at QMC's early look (`key` its key, `early` its values): `(evaluations
    spent, the CornerMap or None)`. Nothing is spent in one dimension (a face is a corner,
    which `_edged_grid` bends)."""
    if lo.ndim == 0 or lo.shape[0] < 2:
        return 0, None
    log2_size = (per_replica // 4).bit_length() - 1
    points = jax.tree_util.Partial(net_points, key, lo, hi, 0, 1, log2_size)
    corner, singular = corner_probe(f, batched, lo, hi, points, early)
    return corner_probe_evaluations(lo.shape[0]), (corner if bool(singular) else None)


def with_corner_candidate(result, key, f, lo, hi, probe, *, batched, per_replica):
    """The pilot's `result` (`run_pilot`'s) with QMC through the corner map among its
    candidates (`probe`: `seek_corner`'s), on nets as large as QMC's pilot's, taken from the
    stream's evaluations; QMC through the trained grid is then none where the grid is not
    bent at the corner (`bends_corner`). Where no corner was found, the probe's evaluations
    count in QMC's."""
    pilot, state, mixture, rest = result
    spent, corner = probe
    if corner is None:
        return charged_to_qmc(pilot, spent), state, mixture, rest - spent
    if pilot.candidates[int(pilot.choice)] == "grid_qmc" and not bool(
            bends_corner(corner, *edge_powers(state.grid))):
        # Through a grid whose density stays bounded at the corner, f/q is unbounded there:
        # a power-law tail that its nets missed, as the rays show.
        pilot = dropped(pilot, "grid_qmc")
    spent += per_replica * QMC_REPLICAS
    growth = min(final_net(rest - spent, BENT_REPLICAS) / per_replica, MAX_NET_GROWTH)
    figures = grid_qmc_pilot(jax.random.fold_in(key, 2), corner, f=f, per_replica=per_replica,
                             growth=growth, batched=batched)
    pilot = appended(pilot, "corner_qmc", figures.variance, figures.blind, CORNER_COST, spent)
    if int(pilot.choice) == len(pilot.candidates) - 1:
        return pilot, corner, None, rest - spent  # (the map "corner_qmc" streams through)
    return pilot, state, mixture, rest - spent
