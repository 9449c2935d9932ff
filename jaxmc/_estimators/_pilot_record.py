r"""The record of `integrate(method="auto")`'s pilot: what each candidate measured."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._format import concrete, number


class Pilot(eqx.Module):
    """What the pilot of `integrate(method="auto")` measured.

    **Fields:**

    - `candidates`: the methods tried, in order.
    - `variance_per_evaluation`: each one's $m \\sigma^2_m$ (for an array-valued
      integrand, summed over the components, relative to the squared mean; a grid that
      follows a singularity credited for its refining, `credited_for_refining`).
    - `cost`: `variance_per_evaluation` times the relative time per evaluation.
    - `choice`: index of the winner in `candidates`.
    - `evaluations`: integrand evaluations the pilot spent, per candidate (QMC's with those
      of a search for a ridge at its points, `_pilot_ridge`, or for a singular corner,
      `_pilot_corner`, that found none).
    """

    candidates: tuple[str, ...] = eqx.field(static=True)
    variance_per_evaluation: jax.Array
    cost: jax.Array
    choice: jax.Array
    evaluations: tuple[int, ...] = eqx.field(static=True)

    def __repr__(self) -> str:
        """`Pilot(choice='adaptive', qmc=(variance 2.63, cost 2.63, 5120 evaluations), ...)`:
        each candidate's figures (`inf`: blind, unfitted, too loose a fit to compete, values
        with a power-law tail through the grid, or a grid that misses a mode the mixture holds
        or is not bent at a singular corner);
        equinox's repr (shapes and dtypes) when traced, or batched under `vmap`."""
        if not concrete(self) or jnp.ndim(self.choice) != 0:
            return eqx.Module.__repr__(self)
        figures = [
            f"{name}=(variance {number(v)}, cost {number(c)}, {m} evaluations)"
            for name, v, c, m in zip(self.candidates, np.asarray(self.variance_per_evaluation),
                                     np.asarray(self.cost), self.evaluations)
        ]
        chosen = self.candidates[int(self.choice)]
        return f"Pilot(choice={chosen!r}, {', '.join(figures)})"


def charged_to_qmc(pilot: Pilot, evaluations: int) -> Pilot:
    """`pilot` with `evaluations` more in QMC's count: a search at QMC's points that found
    nothing to measure (a ridge, a singular corner)."""
    spent = (pilot.evaluations[0] + evaluations,) + pilot.evaluations[1:]
    return Pilot(pilot.candidates, pilot.variance_per_evaluation, pilot.cost, pilot.choice, spent)


def appended(pilot: Pilot, name: str, variance, blind, relative_cost: float,
             evaluations: int) -> Pilot:
    """`pilot` with one more candidate, `name`, measured at `variance` per evaluation
    (`inf` where `blind`) at `relative_cost` times a Sobol' point's time: chosen where it
    costs less than the winner."""
    variance, cost, choice = _appended(pilot.variance_per_evaluation, pilot.cost, pilot.choice,
                                       variance, blind, relative_cost)
    return Pilot(pilot.candidates + (name,), variance, cost, choice,
                 pilot.evaluations + (evaluations,))


@jax.jit
def _appended(variance, cost, choice, v_new, blind, relative_cost):
    v_new = jnp.where(blind, jnp.inf, v_new.astype(variance.dtype))
    new_cost = relative_cost * v_new
    wins = new_cost < cost[choice]
    return (jnp.concatenate([variance, v_new[None]]), jnp.concatenate([cost, new_cost[None]]),
            jnp.where(wins, variance.shape[0], choice).astype(jnp.int32))


def dropped(pilot: Pilot, name: str) -> Pilot:
    """`pilot` with candidate `name` no candidate (its figures `inf`), the choice the
    cheapest of the rest where it was `name`."""
    variance, cost, choice = _dropped(pilot.variance_per_evaluation, pilot.cost, pilot.choice,
                                      pilot.candidates.index(name))
    return Pilot(pilot.candidates, variance, cost, choice, pilot.evaluations)


@jax.jit
def _dropped(variance, cost, choice, index):
    variance, cost = (a.at[index].set(jnp.inf) for a in (variance, cost))
    return variance, cost, jnp.where(choice == index, jnp.argmin(cost), choice).astype(jnp.int32)
