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
      of a search for a ridge at its points that found none, `_pilot_ridge`).
    """

    candidates: tuple[str, ...] = eqx.field(static=True)
    variance_per_evaluation: jax.Array
    cost: jax.Array
    choice: jax.Array
    evaluations: tuple[int, ...] = eqx.field(static=True)

    def __repr__(self) -> str:
        """`Pilot(choice='adaptive', qmc=(variance 2.63, cost 2.63, 5120 evaluations), ...)`:
        each candidate's figures (`inf`: blind, unfitted, too loose a fit to compete, values
        with a power-law tail through the grid, or a grid that misses a mode the mixture holds);
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
