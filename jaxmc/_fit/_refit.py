r"""Refitting any proposal by an optimistix minimiser on each round's samples."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx

from .._integrand import ratio
from .._stats import estimate_iid
from ._objectives import OBJECTIVES, log_abs, objective_loss
from ._rule import AbstractAdaptation, Integrand, Samples
from ._solvers import check_solver, split_parameters


class RefitState(eqx.Module):
    """The proposal being refitted and the round size."""

    proposal: Any
    n: int = eqx.field(static=True)


class Refit(AbstractAdaptation):
    r"""Refit any proposal on each round's samples: `steps` steps of `solver` on `objective`.

    Round $i$ draws $n$ i.i.d. points from the current proposal $q$, estimates
    the integral (eq. 10/12), and minimises the objective over the proposal's
    parameters on the same evaluations, reweighted from the frozen $q$
    (`fit_on_samples`' objective): no extra integrand evaluations. The default
    `solver` is `fit`'s (BFGS, L-BFGS above 2000 parameters, Adam for a `Flow`).
    A step that goes non-finite keeps the old parameters.
    """

    solver: optx.AbstractMinimiser | None = None
    steps: int = eqx.field(static=True, default=32)
    objective: str = eqx.field(static=True, default="variance")

    def check(self, proposal, n):
        if self.objective not in OBJECTIVES:
            raise ValueError(f"`objective` must be one of {OBJECTIVES}, got {self.objective!r}.")
        check_solver(self.solver, proposal, split_parameters(proposal, None)[0])

    def init(self, key, proposal, n):
        return RefitState(proposal, n)

    def step(self, key, index, state, integrand: Integrand):
        prop, n = state.proposal, state.n
        x, px = prop.sample(jax.random.fold_in(key, index), n)
        fx = integrand(x)
        y, bad = ratio(fx, px)
        est = estimate_iid(y, bad)
        log_q = jnp.log(px)
        samples = Samples(x, fx, log_q, jnp.full((n,), 1.0 / n, log_q.dtype))
        return RefitState(self._refit(prop, x, fx, log_q), n), est, samples

    def _refit(self, prop, x, fx, log_q):
        p0, static = split_parameters(prop, None)
        solver = check_solver(self.solver, prop, p0)

        def loss(p, args):
            xs, logf, lq = args
            w = jnp.full(lq.shape, 1.0 / lq.shape[0], lq.dtype)
            return objective_loss(self.objective, logf, eqx.combine(p, static).log_pdf(xs), w, lq)

        args = (x, log_abs(fx), log_q)
        sol = optx.minimise(loss, solver, p0, args, max_steps=self.steps, throw=False)
        # Keep the old parameters if the step went non-finite.
        ok = jnp.isfinite(loss(sol.value, args))
        p1 = jax.tree.map(lambda a, b: jnp.where(ok, a, b), sol.value, p0)
        return eqx.combine(p1, static)

    def proposal(self, state):
        return state.proposal
