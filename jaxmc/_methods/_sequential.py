r"""A method's run under `vmap`: element after element, not all elements at once.

A stream already fills the device with its own blocks (a step of up to $2^{18}$ points);
vectorising a batch of streams multiplies each step's arrays by the batch and takes them
out of the cache. Under `vmap`, `sequential_run` maps the run over the batch
(`jax.lax.map`); differentiated, it runs as written (a `jax.custom_jvp` whose rule is the
run's own derivative), so `grad` and `vmap` of `grad` are unchanged.
"""

from __future__ import annotations

import dataclasses
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp

from .._checks import is_concrete
from ._method import AbstractMethod, Problem, Run


def sequential_run(method: AbstractMethod, key, problem: Problem, budget: int) -> Run:
    """`method.run(key, problem, budget)`, each element of a `vmap`'s batch in turn (an
    integrand written for one point; one written for a batch runs as written)."""
    operands = (key, method, problem.f, problem.lo, problem.hi, problem.rtol, problem.atol)
    if problem.batched or all(is_concrete(a) for a in jax.tree.leaves(operands)):
        return method.run(key, problem, budget)  # (eagerly: no batch, the run's own programs)
    f, consts = _hoisted(problem.f, jnp.zeros(problem.lo.shape, problem.lo.dtype))
    arrays, static = eqx.partition((method, problem.lo, problem.hi, problem.rtol, problem.atol),
                                   eqx.is_array)

    def run(key, consts, arrays):
        method, lo, hi, rtol, atol = eqx.combine(arrays, static)
        bound = dataclasses.replace(problem, f=lambda x: f(x, *consts), lo=lo, hi=hi,
                                    rtol=rtol, atol=atol)
        return method.run(key, bound, budget)

    @jax.custom_batching.custom_vmap
    def one_by_one(key, consts, arrays):
        return run(key, consts, arrays)

    @one_by_one.def_vmap
    def _(axis_size, in_batched, key, consts, arrays):
        operands = [key, consts, arrays]
        batched, unbatched = eqx.partition(operands, list(in_batched))

        def element(sliced):
            return run(*eqx.combine(sliced, unbatched))

        out = jax.lax.map(element, batched)
        return out, jax.tree.map(lambda _: True, out)

    @jax.custom_jvp
    def differentiable(key, consts, arrays):
        return one_by_one(key, consts, arrays)

    @partial(differentiable.defjvp, symbolic_zeros=True)
    def _(primals, tangents):
        # Only the perturbed inputs are differentiated: the others (the bounds, say) may pass
        # through operations that have no derivative.
        leaves, tree = jax.tree.flatten(primals)
        dleaves = jax.tree.leaves(tangents, is_leaf=_is_zero)
        live = [i for i, t in enumerate(dleaves) if not _is_zero(t)]

        def perturbed(*values):
            full = list(leaves)
            for i, v in zip(live, values):
                full[i] = v
            return run(*jax.tree.unflatten(tree, full))

        return jax.jvp(perturbed, [leaves[i] for i in live], [dleaves[i] for i in live])

    return differentiable(key, tuple(consts), arrays)


def _is_zero(t) -> bool:
    return isinstance(t, jax.custom_derivatives.SymbolicZero)


def _hoisted(f, x):
    """`(g, consts)` with `g(x, *consts) == f(x)` for points shaped as `x`: the values `f`
    closes over (its `args`, a batched parameter of a user's `vmap`) traced out of it as
    arguments. (`jax.closure_convert` keeps the tracers it need not differentiate, which
    `custom_vmap` may not close over.)"""
    closed, shape = jax.make_jaxpr(f, return_shape=True)(x)
    out = jax.tree.structure(shape)

    def g(x, *consts):
        return jax.tree.unflatten(out, jax.core.eval_jaxpr(closed.jaxpr, consts, x))

    return g, closed.consts
