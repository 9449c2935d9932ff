r"""The decisions of `integrate(method="auto")`'s pilot between its stages: each candidate's
cost per unit of variance (`RELATIVE_COST` times its variance per evaluation, see `_auto`),
the choice among those measured so far (`choose`), and the rules that end the pilot early
(`screen_young_grid`: QMC against the young grid; `after_training`: whether a mixture need
be fitted; `mixture_hopeless`: whether its outlook is worth its pilot). Each is one compiled
program: run eagerly, their dozens of small operations were ~1.5 s of compilation in a first
call."""
from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ._pilot_corner import CORNER_COST
from ._pilot_grid import round_figures
from ._pilot_mixture import follows_a_singularity
from ._pilot_nets import QMCFigures, outlook_drops_grid
from ._pilot_record import Pilot
from ._pilot_ridge import RIDGE_COST


CANDIDATES = ("qmc", "adaptive", "grid_qmc", "mixture")
# Time per evaluation, relative to a Sobol' point.
RELATIVE_COST = {"qmc": 1.0, "adaptive": 3.0, "grid_qmc": 2.0, "mixture": 12.0,
                 "ridge_qmc": RIDGE_COST, "corner_qmc": CORNER_COST}
# The lowest relative variance per evaluation expected of a mixture seeded from the
# grid: measured 0.02-0.07 on vegas's and i-flow's Gaussians and camels at 1e5.
MIXTURE_FLOOR = 0.01
OUTLOOK_COSTS = (RELATIVE_COST["adaptive"], RELATIVE_COST["mixture"] * MIXTURE_FLOOR)
# A mixture whose figure on the grid's points (`mixture_outlook`) costs this many times QMC's
# or the grid's is not measured. The ratio, 4 keys at 1e5 and 1e6: 8.9-68 on x^-1/3 in 6-D,
# x^-1/2 in 2-D and (sum x)^-3/2 in 4-D (the measured mixture then cost 6-100x the grid),
# 5.8-8.3 on the 4-D resonance where its grid trained (the mixture measured too loose to
# compete); at most 1.1 where the mixture won or came near (two 4-D Gaussians, the 5-D
# posterior, i-flow's 16-D camel and 8-D Gaussian, vegas's 4-D Gaussian, the 10-D ball).
MIXTURE_HOPELESS = 4.0
# A young grid this much costlier than QMC is not trained on (never under a power-law tail
# of QMC's values, see `screen_young_grid`). Measured after 3 rounds, against QMC's
# projected cost, 4 keys of every `auto` benchmark case that was no clear win, at 1e5 and 1e6: where the
# grid or its mixture then won with QMC's values not heavy-tailed, 0.6-1.5x (two 4-D
# Gaussians; the 10-D ball's QMC saw nothing); where QMC won, 0.9-740x, 3-17x on 16 of
# those 41 runs (camel 4-D, annulus, oblique resonances, 3-D ball, half-space), which
# trained the grid and fitted a mixture at 20x. At 3x, over 10 keys at 1e5, camel 4-D, the
# 12-D resonance and the half-space took 1.7-2x less time, the 4-D resonance 1.2x (the
# estimates unchanged, or from larger nets); the 4-D corner singularity and i-flow's 8-D
# Gaussian (young 80 per evaluation against QMC's 18, then 0.35) kept it at 20 before their
# power-law exemption. With it, 3x -> 2x (keys 100-115 at 1e5, 100-111 at 1e6): the 4-D
# resonance trained the grid on 6 keys of 16 instead of 11 (QMC then won on 3 and 8 of
# them), 2.2x the efficiency at 1e5 and 1.4x at 1e6; the 12-D one 1.2x at 1e5; the 4-D
# camel took QMC on the 3 keys of 16 where QMC through the trained grid had won (RMS error
# 3.7e-4 -> 4.1e-4); the 10-D ball, the 3-D ball, the annulus, the 8-D half-space and
# Genz's 8-D continuous and discontinuous chose as before.
SCREEN_MARGIN = 2.0


def qmc_alone(qmc: QMCFigures, evaluations: int) -> Pilot:
    """The `Pilot` record of a clear QMC win (made inside the figures' compiled program:
    eagerly, its three small arrays cost ~0.1 ms)."""
    v = qmc.variance[None]
    return Pilot(("qmc",), v, v, jnp.asarray(0, jnp.int32), (evaluations,))


def choose(qmc: QMCFigures, variance, blind):
    """`(variance, cost, choice)` of the candidates, given QMC's pilot and every
    candidate's variance per evaluation and blindness (QMC's first)."""
    # A pilot that saw only zeros (a peak its points missed), or whose mean a handful of
    # points carried, measured nothing: it never beats one that measured the integrand.
    # If none did, the grid, which kept looking as it trained, is the better bet.
    variance = jnp.where(blind & ~jnp.all(blind), jnp.inf, variance)
    cost = variance * jnp.asarray([RELATIVE_COST[c] for c in CANDIDATES], variance.dtype)
    choice = jnp.where(qmc.clear_win, 0, jnp.where(jnp.all(blind), 1, jnp.argmin(cost)))
    return variance, cost, choice.astype(jnp.int32)


def first_candidates(choice, k):
    """`(variance, cost, choice)` restricted to the first `k` candidates."""
    return tuple(a[:k] if a.ndim else a for a in choice)


@eqx.filter_jit
def screen_young_grid(qmc: QMCFigures, parts, samples, active, *, rounds, round_size):
    """QMC against the young grid (its rounds' estimates and last `Samples`, `run_rounds`):
    `(its figures, the choice, the choice restricted to the two, whether it is dropped)`."""
    v_grid, grid_blind, _ = round_figures(parts, samples, active, rounds=rounds,
                                          round_size=round_size)
    # Nothing is carried through a young grid, nor seeded from it; one its outlook drops is none.
    v_grid = jnp.where(outlook_drops_grid(qmc, *OUTLOOK_COSTS), jnp.inf, v_grid)
    screened = choose(qmc, jnp.stack([qmc.variance, v_grid, jnp.inf, jnp.inf]),
                       jnp.stack([qmc.blind, grid_blind, True, True]))
    # Dropped only if SCREEN_MARGIN times costlier than QMC as it stands, and never under a
    # power-law tail: there a young grid's rounds are as heavy-tailed as QMC's values, and
    # their variances say nothing of the trained grid's (x^-1/2 in 2-D at 1e6: 35-110
    # after 3 rounds, 0.4-0.6 after 10, against QMC's 5-7 credited as plain MC), nor on a
    # product the trained grid flattens (Genz's 8-D continuous: 0.49 after 3 rounds, 1.8e-6
    # after 10 carried through by QMC, against QMC's 0.05).
    qmc_cost, grid_cost = screened[1][:2]
    decided = (grid_cost > SCREEN_MARGIN * qmc_cost) & ~qmc.blind & ~qmc.heavy & ~qmc.separable
    return (v_grid, grid_blind), screened, first_candidates(screened, 2), decided


@eqx.filter_jit
def after_training(qmc: QMCFigures, v_grid, grid_blind, grid_qmc: QMCFigures, screened,
                    decided):
    """QMC, the trained grid and QMC through it (the screened choice where the grid was
    dropped), and whether no mixture need be fitted: QMC or the grid costs less than any
    measured would (`MIXTURE_FLOOR`; not QMC through the grid: on a grid holding one of two
    separated peaks $f/q$ is smooth and its figure low, and only the mixture's pilot seeks
    the missed peak: i-flow's 16-D camel at 1e5, one key of 10 took it and returned half the
    truth, before this), or the grid follows a singularity (`follows_a_singularity`)."""
    three = choose(qmc, jnp.stack([qmc.variance, v_grid, grid_qmc.variance, jnp.inf]),
                    jnp.stack([qmc.blind, grid_blind, grid_blind | grid_qmc.blind, True]))
    beaten = ~decided & ((jnp.min(three[1][:2]) < RELATIVE_COST["mixture"] * MIXTURE_FLOOR)
                         | follows_a_singularity(qmc, grid_qmc, three[0][1]))
    three = tuple(jnp.where(decided, a, b)
                  for a, b in zip(first_candidates(screened, 3), first_candidates(three, 3)))
    return three, beaten


@jax.jit
def mixture_hopeless(outlook, cost):
    """Whether the mixture, at its figure on the grid's points (`mixture_outlook`), costs
    `MIXTURE_HOPELESS` times as much as QMC or the grid (`cost`: QMC's, the grid's, ...).
    Not QMC through the grid, as for `MIXTURE_FLOOR` (`after_training`)."""
    return RELATIVE_COST["mixture"] * outlook > MIXTURE_HOPELESS * jnp.min(cost[:2])


@eqx.filter_jit
def with_mixture(qmc: QMCFigures, v_grid, grid_blind, grid_qmc: QMCFigures, v_mixture,
                  mixture_blind, grid_misses, screened, decided):
    """The four candidates after training (the screened choice where the grid was dropped);
    a grid that misses a mode the mixture holds (`grid_misses`) is none, nor QMC through it."""
    measured = jnp.isfinite(v_mixture) & ~mixture_blind
    misses = grid_misses & measured
    v_grid = jnp.where(misses, jnp.inf, v_grid)
    v_grid_qmc = jnp.where(misses, jnp.inf, grid_qmc.variance)
    trained = choose(qmc, jnp.stack([qmc.variance, v_grid, v_grid_qmc, v_mixture]),
                      jnp.stack([qmc.blind, grid_blind, grid_blind | grid_qmc.blind,
                                 grid_blind | mixture_blind]))
    return tuple(jnp.where(decided, a, b) for a, b in zip(screened, trained))
