r"""The record of `Auto`'s pilot: what each candidate measured, and which stages ran."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._format import concrete, number


STAGES = ("early look", "whole nets", "grid", "mixture")


class Pilot(eqx.Module):
    r"""What the pilot of `Auto` measured (`IntegrationEstimate.pilot`).

    **Fields:**

    - `candidates`: the methods raced, in order.
    - `variance`: each one's relative variance per evaluation $m\sigma^2_m / I^2$ as its
      pilot measured it (QMC's projected to its stream's nets; `inf` where unmeasured:
      a stage that did not run, a pilot that saw nothing, too loose a fit).
    - `log_sd`: the standard deviation of each figure's logarithm.
    - `cost`: `variance` times the candidate's time per evaluation (`Auto.costs`): the
      figure of merit, a time per unit of variance.
    - `choice`: index of the winner in `candidates`.
    - `stages`: whether each of `STAGES` ran (the early look always does).
    - `evaluations`: integrand evaluations the pilot spent (counted in the result's `n`,
      not in its mean).
    """

    candidates: tuple[str, ...] = eqx.field(static=True)
    variance: jax.Array
    log_sd: jax.Array
    cost: jax.Array
    choice: jax.Array
    stages: jax.Array
    evaluations: jax.Array

    def __repr__(self) -> str:
        """`Pilot(choice='grid_qmc', stages=..., evaluations=..., qmc=(variance ..., cost ...), ...)`;
        equinox's repr (shapes and dtypes) when traced, or batched under `vmap`."""
        if not concrete(self) or jnp.ndim(self.choice) != 0:
            return eqx.Module.__repr__(self)
        ran = [name for name, on in zip(STAGES, np.asarray(self.stages)) if on]
        figures = [
            f"{name}=(variance {number(v)} x/ exp({number(s, '.2g')}), cost {number(c)})"
            for name, v, s, c in zip(self.candidates, np.asarray(self.variance),
                                     np.asarray(self.log_sd), np.asarray(self.cost))
        ]
        return (f"Pilot(choice={self.candidates[int(self.choice)]!r}, stages={ran}, "
                f"evaluations={int(self.evaluations)}, {', '.join(figures)})")
