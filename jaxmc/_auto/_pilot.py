r"""The record of `Auto`'s pilot: what each candidate measured, and which stages ran."""

from __future__ import annotations

import math

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

    def table(self) -> str:
        """The race as a text table: per candidate its variance per evaluation (relative, and
        the factor of its uncertainty, one standard deviation), its cost and whether it won;
        then the stages that ran. Outside `jit`, unbatched."""
        if not concrete(self) or jnp.ndim(self.choice) != 0:
            raise ValueError("`summary()` needs concrete, unbatched values: call it outside "
                             "`jit` and `vmap`.")
        head = ("candidate", "variance/eval", "x/ (1 sd)", "cost", "")
        rows = [
            (name, f"{float(v):.3g}", f"{math.exp(float(s)):.3g}" if np.isfinite(s) else "-",
             f"{float(c):.3g}", "<- won" if i == int(self.choice) else "")
            for i, (name, v, s, c) in enumerate(zip(
                self.candidates, np.asarray(self.variance), np.asarray(self.log_sd),
                np.asarray(self.cost)))
        ]
        widths = [max(len(r[j]) for r in [head, *rows]) for j in range(len(head))]
        lines = ["  ".join(c.ljust(w) if j == 0 else c.rjust(w)
                           for j, (c, w) in enumerate(zip(r, widths))).rstrip()
                 for r in [head, *rows]]
        ran = [name for name, on in zip(STAGES, np.asarray(self.stages)) if on]
        return "\n".join([*lines, f"stages run: {', '.join(ran)}; "
                           f"{int(self.evaluations):,} evaluations"])
