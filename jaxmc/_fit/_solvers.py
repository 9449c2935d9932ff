"""The optimistix side of fitting: which parameters, which solver, and the step loops.

`fit` optimises a proposal's inexact-array leaves apart from its box
(`parameter_spec`, `eqx.partition`/`eqx.combine`); the default solver is BFGS
(L-BFGS for many parameters, Adam for flows); `run_steps` drives a solver's
`init`/`step` for a fixed number of steps on fresh batches.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
import optimistix as optx

from ..proposals import Flow


def parameter_spec(proposal: Any) -> Any:
    """The filter spec `fit` optimises: inexact arrays, except the box bounds `lo`/`hi`."""

    def is_param(path, leaf):
        if not eqx.is_inexact_array(leaf):
            return False
        name = getattr(path[-1], "name", None) if path else None
        return name not in ("lo", "hi")

    return jax.tree_util.tree_map_with_path(is_param, proposal)


# Above this many parameters the default is L-BFGS: BFGS keeps a dense inverse Hessian
# (~10^4 parameters would need ~10^8 entries).
_DENSE_BFGS_MAX = 2000
# Flows' default, as in neural importance sampling (Müller et al. 2019): Adam on fresh
# samples at every step, for a fixed number of steps.
_FLOW_LEARNING_RATE = 3e-3
# One object: the solver is part of a compiled fit's cache key, and `optax.adam` builds
# new functions on every call (a new solver would compile the fit anew).
_FLOW_SOLVER = optx.OptaxMinimiser(optax.adam(_FLOW_LEARNING_RATE), rtol=0.0, atol=0.0)


def _has_flow(proposal) -> bool:
    """Whether `proposal` is, or contains (e.g. in a `Mixture`), a `Flow`."""
    is_flow = lambda node: isinstance(node, Flow)
    return any(is_flow(n) for n in jax.tree_util.tree_leaves(proposal, is_leaf=is_flow))


def default_solver(proposal, params):
    if _has_flow(proposal):
        return _FLOW_SOLVER
    size = sum(int(x.size) for x in jax.tree_util.tree_leaves(params))
    if size > _DENSE_BFGS_MAX:
        return optx.LBFGS(rtol=1e-5, atol=1e-5)
    return optx.BFGS(rtol=1e-5, atol=1e-5)


def check_solver(solver, proposal, params):
    if solver is None:
        return default_solver(proposal, params)
    if not isinstance(solver, optx.AbstractMinimiser):
        raise TypeError(
            f"`solver` must be an optimistix.AbstractMinimiser (e.g. optimistix.BFGS), "
            f"got {type(solver).__name__}."
        )
    return solver


def split_parameters(proposal, filter_spec):
    spec = parameter_spec(proposal) if filter_spec is None else filter_spec
    params, static = eqx.partition(proposal, spec)
    if not jax.tree_util.tree_leaves(params):
        raise ValueError(
            f"`proposal` ({type(proposal).__name__}) has no parameters to fit "
            "(no inexact-array leaves besides lo/hi)."
        )
    return params, static


def minimise(loss, solver, params, args, max_steps, throw=False):
    sol = optx.minimise(loss, solver, params, args, max_steps=max_steps, throw=throw)
    return sol.value, sol.result, sol.stats["num_steps"]


def run_steps(fn_args, loss, solver, params, max_steps, steps_per_batch=1):
    """`max_steps` solver steps, with fresh `args` every `steps_per_batch` steps.

    `fn_args(batch, params) -> args` draws a batch's base randomness (from a key
    folded with the batch index) or its frozen samples (from the current
    proposal); the batch then serves `steps_per_batch` consecutive steps, so an
    expensive integrand is evaluated once per batch. A step whose loss or new
    parameters are not finite is skipped. Returns the parameters and the loss at
    every step.
    """
    aux_fn = lambda y, args: (loss(y, args), None)
    args0 = fn_args(0, params)
    f_struct = jax.eval_shape(lambda: loss(params, args0))
    state = solver.init(
        fn=aux_fn, y=params, args=args0, options={}, f_struct=f_struct, aux_struct=None,
        tags=frozenset(),
    )

    def step(carry, _, args):
        y, st = carry
        value = loss(y, args)
        y_new, st_new, _ = solver.step(
            fn=aux_fn, y=y, args=args, options={}, state=st, tags=frozenset()
        )
        # A step that went non-finite (a degenerate batch, an overflow) is skipped: one
        # NaN in the parameters would otherwise end the fit for good.
        ok = jnp.isfinite(value) & jnp.all(
            jnp.stack([jnp.all(jnp.isfinite(a)) for a in jax.tree_util.tree_leaves(y_new)])
        )
        keep = lambda new, old: jnp.where(ok, new, old)
        return (jax.tree.map(keep, y_new, y), jax.tree.map(keep, st_new, st)), value

    def batch(carry, b):
        args = fn_args(b, carry[0])
        return jax.lax.scan(lambda c, i: step(c, i, args), carry, None, length=steps_per_batch)

    batches = max_steps // steps_per_batch
    (params, _), losses = jax.lax.scan(batch, (params, state), jnp.arange(batches))
    return params, jnp.reshape(losses, (max_steps,))
