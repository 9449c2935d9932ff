r"""Adaptation rules as objects, and the one loop that runs any of them.

An adaptation rule (blackjax's kernel style) is an `AbstractAdaptation`:
`init(key, proposal, n)` builds its state from a starting proposal, and
`step(key, index, state, integrand)` runs one round — draw `n` points,
evaluate the integrand, estimate the integral, adapt — returning the new
state, the round's `Estimate` and the round's weighted `Samples`.
`run_adaptation` is a `lax.scan` over rounds that knows nothing about any
particular rule: VEGAS, VEGAS+, the partition's growth and optimistix
refitting are each one class, and a new rule is a new class.
"""

from __future__ import annotations

import abc
import functools
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from .._integrand import evaluate
from .._progress import report
from .._stats import Estimate


class Integrand(eqx.Module):
    """An integrand and how to call it: `f(x)` for one point, or the whole batch if `batched`.

    `f` is a pytree leaf, not static metadata: an integrand that carries arrays
    (an equinox Module, or `f` bound to `args`) has them traced under
    `equinox.filter_jit`, so new values reuse the compiled code.
    """

    f: Callable
    batched: bool = eqx.field(static=True, default=False)

    def __call__(self, x: jax.Array) -> jax.Array:
        """`f` on a batch `x` `(n, ...)` -> `(n, *out_shape)`, floating."""
        return evaluate(self.f, x, self.batched)


class Samples(eqx.Module):
    r"""One round's evaluated points, weighted so that they estimate integrals.

    $\sum_i w_i\, g(x_i)/q(x_i) \approx \int g$ for any $g$, with $q$ the
    density the points were drawn from and weights $w_i$ summing to one
    ($1/n$ for i.i.d. draws; $v_h/n_h$ for a stratified draw with $n_h$
    points in a stratum of relative volume $v_h$). So $|f(x_i)|\,w_i/q(x_i)$
    are importance weights of the points for the density $\propto |f|$ (what
    `GaussianMixture.from_samples` fits), and the fields are what
    `fit_on_samples` takes.

    **Fields:** `x` `(n, d)` (or `(n,)`), `fx` `(n, ...)`, `log_q` `(n,)`, `weights` `(n,)`.
    """

    x: jax.Array
    fx: jax.Array
    log_q: jax.Array
    weights: jax.Array

    def importance_weights(self) -> jax.Array:
        r"""$|f(x_i)|\,w_i/q(x_i)$ (the Euclidean norm of an array-valued $f$), normalised to sum to one."""
        fx = jnp.reshape(self.fx, (self.fx.shape[0], -1))
        w = jnp.sqrt(jnp.sum(fx**2, axis=-1)) * self.weights * jnp.exp(-self.log_q)
        w = jnp.where(jnp.isfinite(w), w, 0.0)
        return w / jnp.maximum(jnp.sum(w), jnp.finfo(w.dtype).tiny)


class AbstractAdaptation(eqx.Module):
    """An adaptation rule: `init` a state from a proposal, `step` one round, read the proposal back.

    Subclasses are immutable configurations (damping, allocation exponent,
    solver, ...); everything that changes from round to round is in the state,
    a pytree whose non-array parts stay fixed.
    """

    def check(self, proposal: Any, n: int) -> None:
        """Trace-time validation of the starting proposal and the round size (raise `ValueError`)."""

    @abc.abstractmethod
    def init(self, key: jax.Array, proposal: Any, n: int) -> Any:
        """The state before round 0, for rounds of `n` evaluations."""

    @abc.abstractmethod
    def step(
        self, key: jax.Array, index: jax.Array, state: Any, integrand: Integrand
    ) -> tuple[Any, Estimate, Samples]:
        """Round `index` (its randomness from `fold_in(key, index)`): `(state, estimate, samples)`."""

    @abc.abstractmethod
    def proposal(self, state: Any) -> Any:
        """The adapted proposal held by `state`."""


def _report_round(mean, stderr, done, last, *, total: int) -> None:
    """Host side: a round's estimate to the progress bar."""
    report(mean, stderr, done, total=total, last=bool(last), desc="adapt")


def run_adaptation(
    rule: AbstractAdaptation,
    key: jax.Array,
    integrand: Integrand,
    proposal: Any,
    iterations: int,
    n: int,
    *,
    keep_samples: bool = False,
    progress: bool = False,
    active: jax.Array | None = None,
) -> tuple[Estimate, Any, Samples | None]:
    """`iterations` rounds of `rule` in one `lax.scan` (with `progress`, each round's
    estimate is sent to the progress bar, `jaxmc._progress.report`).

    With `active` (a traced count), only the first `active` rounds run; the rest
    leave the state and the kept samples as they were and estimate zeros, so one
    compiled program serves any number of rounds up to `iterations`.

    **Returns:** the per-round estimates (stacked), the rule's final state
    (`rule.proposal(state)` is the adapted proposal), and, with `keep_samples`,
    the last round's `Samples` (else `None`).
    """
    rule.check(proposal, n)
    state = rule.init(key, proposal, n)
    carry, static = eqx.partition(state, eqx.is_array)

    def round_(carry, i):
        new_state, est, samples = rule.step(key, i, eqx.combine(carry, static), integrand)
        new_carry, _ = eqx.partition(new_state, eqx.is_array)
        if progress:  # (the last round closes a bar opened under a user's `jit`)
            jax.debug.callback(functools.partial(_report_round, total=iterations * n),
                               est.mean, est.stderr, (i + 1) * n, i == iterations - 1)
        return new_carry, (est, samples)

    zeros = lambda shapes: jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)  # noqa: E731
    no_estimate, no_samples = zeros(jax.eval_shape(lambda c: round_(c, jnp.int32(0))[1], carry))

    if active is not None:
        return _run_active(round_, carry, static, no_estimate, no_samples, iterations, active,
                           keep_samples)

    if not keep_samples:

        def round_estimate(c, i):
            new_carry, (est, _) = round_(c, i)
            return new_carry, est

        carry, parts = jax.lax.scan(round_estimate, carry, jnp.arange(iterations))
        return parts, eqx.combine(carry, static), None

    # Carry the latest round's samples (not stacked over rounds: bounded memory).
    def round_keep(c, i):
        new_carry, (est, samples) = round_(c[0], i)
        return (new_carry, samples), est

    (carry, samples), parts = jax.lax.scan(round_keep, (carry, no_samples), jnp.arange(iterations))
    return parts, eqx.combine(carry, static), samples


def _run_active(round_, carry, static, no_estimate, no_samples, iterations, active, keep_samples):
    """`run_adaptation`'s rounds up to a traced count `active`: a `while_loop` that writes each
    round's estimate into the stacked zeros of all `iterations` (a `scan` whose later rounds
    `cond` skipped would still copy its carry through each of them). Not
    reverse-differentiable: the fits it serves are held fixed."""
    stacked = jax.tree.map(lambda z: jnp.zeros((iterations,) + z.shape, z.dtype), no_estimate)

    def body(loop):
        i, c, samples, parts = loop
        c, (est, new_samples) = round_(c, i)
        parts = jax.tree.map(lambda a, e: a.at[i].set(e), parts, est)
        return i + 1, c, new_samples if keep_samples else samples, parts

    start = (jnp.int32(0), carry, no_samples if keep_samples else None, stacked)
    limit = jnp.minimum(active, iterations)
    _, carry, samples, parts = jax.lax.while_loop(lambda loop: loop[0] < limit, body, start)
    return parts, eqx.combine(carry, static), samples
