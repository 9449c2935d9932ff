r"""`Auto`'s race: which candidates can still win, which stages are then worth running, and
the winner.

The figure of merit is the cost of a unit of variance: a candidate $k$ whose relative
variance per evaluation is $v_k$ and whose time per evaluation is $c_k$ (relative to a
Sobol' point) gives variance about $v_k/n$ from $n$ more evaluations at time $c_k n$, so
the winner minimises $c_k v_k$. Each figure is an estimate with an uncertainty
(`Figure.log_sd`): at `z` standard deviations it gives an optimistic and a pessimistic
bound.

A stage (the grid's training and what is measured on it) costs evaluations that its
candidates' streams then lack: a candidate measured after it streams $B_1$ evaluations
where the leader could stream $B_0 > B_1$ now, so it wins only if $c_k v_k B_0/B_1 < c_L
v_L$. Before the stage its candidates have only an outlook (what a density fitted to the
pilot's values does on values it was not fitted to); the stage runs unless every one of
them is hopeless: its optimistic bound, at that price, above the leader's pessimistic one.

Under `vmap`, `integrate` runs the members one after another, each with its own choice;
only an integrand written for a batch is vectorised. There each decision is pooled over
the batch, so every member takes the same path: a stage runs if any member would run it,
and the winner minimises the geometric mean of the members' costs.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ._figures import Figure
from ._nets import NetFigures


CANDIDATES = ("qmc", "adaptive", "grid_qmc", "importance")
QMC, ADAPTIVE, GRID_QMC, IMPORTANCE = range(len(CANDIDATES))


def grid_can_win(nets: NetFigures, costs, price, z) -> jax.Array:
    r"""Whether a candidate that needs the grid (its training, `price` = $B_0/B_1$) can still
    beat QMC, from QMC's pilot `nets`.

    The grid's outlook $v_O$ is a product density's, as VEGAS's grid converges to
    (`product_outlook`). The grid alone would cost $c_A v_O$ against QMC's $c_Q v_Q$. QMC
    through the grid gains over QMC what the grid's density gains over uniform sampling,
    $v_O/v_P$ ($v_P$ plain Monte Carlo's on the same points), if QMC's gain on $f$ carries
    over to $f/q$: it costs $c_G v_O v_Q/v_P$ against $c_Q v_Q$, whatever QMC's own figure. A
    mixture is seeded from the grid: it needs the same stage. Where QMC's values saw nothing,
    or have a power-law tail (their outlook's variance has no finite estimate), or QMC's own
    figure is no number, the grid can always win.
    """
    low = nets.outlook.low(z) * price
    adaptive = costs[ADAPTIVE] * low < costs[QMC] * nets.qmc.high(z)
    through_grid = costs[GRID_QMC] * low < costs[QMC] * nets.plain.high(z)
    unread = nets.blind | nets.heavy | ~jnp.isfinite(nets.qmc.value)
    return adaptive | through_grid | unread


def mixture_can_win(outlook, costs, figures: Figure) -> jax.Array:
    """Whether the mixture seeded from the grid, at its `outlook` (its relative variance per
    evaluation read on the grid's points it was fitted to: optimistic), could cost less than
    the cheapest of the measured candidates' `figures`. Its stage's evaluations are set
    aside either way: only time is at stake."""
    measured = costs[:IMPORTANCE] * figures.value[:IMPORTANCE]
    return costs[IMPORTANCE] * outlook < jnp.min(measured)


def pooled_any(flag):
    """`flag` itself; under `vmap`, whether any element's flag is set (unbatched)."""
    return _pooled_any(jax.lax.stop_gradient(flag))


@jax.custom_batching.custom_vmap
def _pooled_any(flag):
    return flag


@_pooled_any.def_vmap
def _pooled_any_batched(axis_size, in_batched, flag):
    return (jnp.any(flag, axis=0) if in_batched[0] else flag), False


@jax.custom_batching.custom_vmap
def pooled_choice(cost):
    """`argmin(cost)`; under `vmap`, the argmin of the sum of the elements' `log(cost)`."""
    return jnp.argmin(cost).astype(jnp.int32)


@pooled_choice.def_vmap
def _pooled_choice_batched(axis_size, in_batched, cost):
    if not in_batched[0]:
        return jnp.argmin(cost).astype(jnp.int32), False
    return jnp.argmin(jnp.sum(jnp.log(cost), axis=0)).astype(jnp.int32), False


def choose(figures: Figure, costs, blind) -> jax.Array:
    """The winner: the least `costs * figures.value` among the candidates that saw the
    integrand (`blind` ones never beat one that did); if none did, the grid, which kept
    looking as it trained. Pooled over a `vmap`'s batch."""
    # (A choice has no derivative: the figures' are not asked for.)
    cost = jnp.where(blind, jnp.inf, jax.lax.stop_gradient(figures.value) * costs)
    none = jnp.all(~jnp.isfinite(cost), axis=-1)
    # (An element that saw nothing votes for the grid.)
    fallback = jnp.where(jnp.arange(cost.shape[-1]) == ADAPTIVE, 1.0, jnp.inf)
    return pooled_choice(jnp.where(none, fallback, cost))
