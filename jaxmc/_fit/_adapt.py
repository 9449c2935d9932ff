r"""`adapt`: rounds of an adaptation rule, combined; `chain`: stages whose samples seed the next."""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx

from .._checks import (
    MAX_COUNT,
    check_callable,
    check_choice,
    check_count,
    check_flag,
    check_key,
    is_concrete,
)
from .._combine import Combined, combine
from .._diagnostics import warn_if_unreliable
from .._integrand import bind
from .._progress import progress_bar
from .._stats import Estimate, ReliabilityWarning, estimate_fields
from ..proposals import GaussianMixture, Grid, Partition, check_proposal
from ._miser import PartitionGrowth
from ._objectives import OBJECTIVES
from ._refit import Refit
from ._rule import AbstractAdaptation, Integrand, Samples, run_adaptation
from ._vegas import MAX_STRATA, Vegas, VegasPlus


# Compiled once per integrand, rule, proposal structure and sizes: `adapt` and `chain` run
# again for new keys, starting proposals or `args` without tracing anew.
_compiled_adaptation = eqx.filter_jit(run_adaptation)


def _check_fraction(value, name: str, lo: float = 0.0, hi: float = math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not lo <= value <= hi:
        raise ValueError(f"`{name}` must be a number in [{lo}, {hi}], got {value!r}.")
    return float(value)


def default_rule(
    proposal: Any,
    *,
    alpha: float = 0.5,
    stratify: bool | None = None,
    beta: float = 0.75,
    max_strata: int = 2**16,
    passes: int = 4,
    solver: optx.AbstractMinimiser | None = None,
    fit_steps: int = 32,
    objective: str = "variance",
) -> AbstractAdaptation:
    """The rule `adapt` uses for `proposal`: `VegasPlus` for a `Grid` (`Vegas` with
    `stratify=False`), `PartitionGrowth` for a `Partition`, `Refit` for any other proposal."""
    if stratify is None:
        stratify = isinstance(proposal, Grid)  # VEGAS+ by default, as in vegas 6
    if stratify and not isinstance(proposal, Grid):
        raise ValueError(
            f"`stratify=True` needs a Grid proposal (VEGAS+), got {type(proposal).__name__}."
        )
    if isinstance(proposal, Grid):
        return VegasPlus(alpha, beta, max_strata) if stratify else Vegas(alpha)
    if isinstance(proposal, Partition):
        return PartitionGrowth(beta, passes)
    return Refit(solver, fit_steps, objective)


def adapt(
    key: jax.Array,
    f: Callable,
    proposal: Any,
    *,
    iterations: int,
    n_per_iteration: int,
    warmup: int = 0,
    alpha: float = 0.5,
    stratify: bool | None = None,
    beta: float = 0.75,
    max_strata: int = 2**16,
    passes: int = 4,
    solver: optx.AbstractMinimiser | None = None,
    fit_steps: int = 32,
    objective: str = "variance",
    batched: bool = False,
    rule: AbstractAdaptation | None = None,
    args: Any = None,
    progress: bool = False,
) -> tuple[Combined, Any]:
    r"""Adaptive importance sampling in the style of vegas: sample, estimate, refit, combine.

    Each of `iterations` rounds of an adaptation rule (`AbstractAdaptation`) draws `n_per_iteration` points from the current
    proposal, estimates the integral from them (the importance estimator,
    eq. 10/12), and refits the proposal on the same evaluations:

    - a `Grid` by the VEGAS rule (`Grid.refine` with damping `alpha`, on the
      weights $(f/p)^2$); by default (`stratify=None` or `True`; `False` for
      plain VEGAS) the unit cube of the grid's map is also cut into hypercubes (about $n/8$ of them, as vegas does) and the
      samples are spread over them: a quarter evenly (at least two per cube),
      the rest $\propto \sigma_h^\beta$ (adaptive stratified sampling of VEGAS+,
      Lepage 2021), $\sigma_h$ the previous round's standard deviation of $f/p$
      in hypercube $h$;
    - a `Partition` is always sampled stratified: each leaf (cell) gets two
      points, a quarter of the rest evenly and the rest
      $\propto (V_c\sigma_c)^\beta$ ($V_c$ its volume, $\sigma_c$ the pooled
      standard deviation of $f$ in it; Neyman allocation at $\beta = 1$);
      then `passes` times on the round's points, the leaves with the largest
      $V_c\sigma_c$ (and coarse leaves next to them) are halved along their
      longest edge, as many as `max_cells` allows, and the cell masses are
      set to $\propto V_c \sqrt{\overline{f^2}}$ (MISER-like recursive
      stratified sampling, Press & Farrar 1990). Needs `n_per_iteration >=
      4 * max_cells`;
    - any other proposal by `fit_steps` steps of `solver` (default as for
      `fit`: BFGS, L-BFGS above 2000 parameters, Adam for a `Flow`) on the
      round's samples, reweighted from the frozen density they came from
      (`fit_on_samples`): no extra integrand evaluations.

    The rounds are then combined by `combine(parts, sequential=True)`: inverse-variance
    weights, each round's taken from the round before it (fixed before the round drew:
    a round's own variance would favour the rounds that came out low), so the
    result carries `chi2_dof` and `q` — a tiny `q` says the rounds disagree, e.g.
    because the early ones missed a peak, and outside `jit` a `q` below 1e-3
    warns with `jaxmc.ReliabilityWarning` — and the per-round estimates in
    `parts`. The first `warmup` rounds (whose density was still poor) are left
    out of the combination (and of `parts`); they still train the proposal.

    The loop is a `lax.scan` with static sizes, so `adapt` works under `jax.jit`
    and `jax.vmap` (e.g. over a parameter in `args`: a family of integrals in
    one compiled call). It is compiled once per integrand object `f`, rule and
    sizes: a second call with new `args` (or a new key or starting proposal)
    reuses the compiled loop, a new closure compiles anew. Pass the returned
    proposal back in to reuse it for a related integrand.

    **Arguments:**

    - `key`: a PRNG key (round `i` uses `fold_in(key, i)`).
    - `f`: the integrand, written for one point (or a batch with `batched=True`).
    - `proposal`: the starting proposal (`Grid`, `GaussianMixture`, `Flow`, ...).
    - `iterations`: number of rounds (static int >= 1).
    - `n_per_iteration`: integrand evaluations per round (static int).
    - `warmup`: rounds left out of the combination (`0 <= warmup < iterations`).
    - `alpha`: VEGAS damping exponent for `Grid` (vegas's default 0.5).
    - `stratify`, `beta`, `max_strata`: VEGAS+ stratification for `Grid` (on by
      default; `stratify=False` gives plain VEGAS)
      (`beta = 0` gives uniform allocation; at most `max_strata <= 2**22`
      hypercubes).
    - `passes`: rounds of cell splitting per iteration for `Partition`
      (static int >= 1; each can double the number of cells).
    - `solver`, `fit_steps`, `objective`: refitting of non-`Grid` proposals.
    - `batched`: `f` takes a batch.
    - `rule`: an adaptation rule (`Vegas`, `VegasPlus`, `PartitionGrowth`,
      `Refit`, or your own `AbstractAdaptation`) to use instead of the one
      the options above choose for the proposal (`default_rule`).
    - `args`: parameters of `f` (any pytree); if given, `f` is called as
      `f(x, args)` (see `jaxmc.integrate`).
    - `progress`: show a progress bar (tqdm, on stderr) with each round's
      estimate (outside `jit`; under a user's `jit` the first round opens it).

    **Returns:** `(combined, proposal)` — a `Combined` and the adapted proposal.

    !!! Example

        ```python
        f = lambda x: jnp.exp(-100 * jnp.sum((x - 0.5) ** 2))
        grid = jaxmc.proposals.Grid(jnp.zeros(4), jnp.ones(4), bins=64)
        est, grid = jaxmc.fit.adapt(jax.random.key(0), f, grid, iterations=10,
                                    n_per_iteration=10_000, warmup=3)
        est.mean, est.stderr, est.chi2_dof, est.q
        ```
    """
    key = check_key(key)
    f = bind(check_callable(f), args)
    proposal = check_proposal(proposal, methods=("sample", "log_pdf"))
    iterations = check_count(iterations, "iterations")
    n = check_count(n_per_iteration, "n_per_iteration", minimum=2, maximum=MAX_COUNT)
    warmup = check_count(warmup, "warmup", minimum=0)
    if warmup >= iterations:
        raise ValueError(f"`warmup` must be < `iterations` = {iterations}, got {warmup}.")
    if iterations * n > MAX_COUNT:
        raise ValueError(
            f"`iterations` * `n_per_iteration` = {iterations * n:,} evaluations must be at most "
            "2**31 - 1 (counts are int32)."
        )
    if rule is None:
        alpha = _check_fraction(alpha, "alpha")
        beta = _check_fraction(beta, "beta")
        max_strata = check_count(max_strata, "max_strata")
        if max_strata > MAX_STRATA:
            raise ValueError(f"`max_strata` must be at most 2**22, got {max_strata}.")
        rule = default_rule(
            proposal,
            alpha=alpha,
            stratify=stratify,
            beta=beta,
            max_strata=max_strata,
            passes=check_count(passes, "passes"),
            solver=solver,
            fit_steps=check_count(fit_steps, "fit_steps"),
            objective=check_choice(objective, "objective", OBJECTIVES),
        )
    elif not isinstance(rule, AbstractAdaptation):
        raise TypeError(f"`rule` must be an AbstractAdaptation, got {type(rule).__name__}.")
    progress = check_flag(progress, "progress")
    with progress_bar(progress, iterations * n, desc="adapt"):
        parts, state, _ = _compiled_adaptation(
            rule, key, Integrand(f, batched), proposal, iterations, n, progress=progress
        )
    parts = jax.tree.map(lambda a: a[warmup:], parts)
    return _warn_if_rounds_disagree(combine(parts, sequential=True)), rule.proposal(state)


# Below this Q the rounds' estimates are inconsistent with one integral (vegas's rule of thumb).
_Q_ALARM = 1e-3


def _warn_if_rounds_disagree(combined: Combined) -> Combined:
    """Outside `jit`, warn when the rounds disagree: typically early rounds missed a peak."""
    if is_concrete(combined.q) and float(combined.q) < _Q_ALARM:
        warnings.warn(
            f"the adaptive rounds disagree (chi2/dof = {float(combined.chi2_dof):.3g}, "
            f"Q = {float(combined.q):.2g}): early rounds probably missed part of the integrand, "
            "so the combined error bar cannot be trusted. Leave them out with `warmup`, or run "
            "more or larger rounds.",
            ReliabilityWarning,
            stacklevel=3,
        )
    # The other diagnostics (the q above is said in adaptive terms).
    warn_if_unreliable(Estimate(**estimate_fields(combined)), "adapt", stacklevel=4)
    return combined


class Stage(eqx.Module):
    """One stage of `chain`: `iterations` rounds of `rule` with `n_per_iteration` evaluations each.

    **Fields:**

    - `rule`: the adaptation rule (e.g. `VegasPlus()`, `Refit()`).
    - `iterations`, `n_per_iteration`: as for `adapt`.
    - `warmup`: the stage's first rounds left out of the combination.
    - `seed`: `None` to continue from the previous stage's proposal, or a callable
      `(previous_proposal, samples) -> proposal` building this stage's starting
      proposal from the previous stage's last round (`Samples`), e.g.
      `seed_gaussian_mixture(8)`.
    """

    rule: AbstractAdaptation
    iterations: int = eqx.field(static=True)
    n_per_iteration: int = eqx.field(static=True)
    warmup: int = eqx.field(static=True, default=0)
    seed: Callable | None = eqx.field(static=True, default=None)


def seed_gaussian_mixture(components: int = 8, **options) -> Callable:
    r"""A `Stage.seed` fitting a `GaussianMixture` to the previous stage's samples by EM.

    The samples' importance weights $|f|\,w/q$ (`Samples.importance_weights`)
    make them a weighted sample of the density $\propto |f|$;
    `GaussianMixture.from_samples(x, weights, lo, hi, components, **options)`
    fits the mixture to it (its modes seed the components).
    """
    components = check_count(components, "components")

    def seed(previous: Any, samples: Samples) -> GaussianMixture:
        return GaussianMixture.from_samples(
            samples.x, samples.importance_weights(), previous.lo, previous.hi, components,
            **options,
        )

    return seed


def chain(
    key: jax.Array,
    f: Callable,
    proposal: Any,
    stages: Sequence[Stage],
    *,
    batched: bool = False,
    args: Any = None,
) -> tuple[Combined, Any]:
    r"""Run adaptation stages one after another; each stage can be seeded by the last one's samples.

    Stage $s$ runs `stage.rule` for `stage.iterations` rounds (randomness from
    `fold_in(key, s)`), starting from the previous stage's proposal, or from
    `stage.seed(previous_proposal, samples)` built on the previous stage's last
    round — e.g. a VEGAS+ grid finds the peaks, then a Gaussian mixture seeded
    from the grid's weighted samples is refitted:

    ```python
    stages = [
        jaxmc.fit.Stage(jaxmc.fit.VegasPlus(), iterations=6, n_per_iteration=20_000, warmup=2),
        jaxmc.fit.Stage(jaxmc.fit.Refit(steps=16), iterations=4, n_per_iteration=20_000,
                        seed=jaxmc.fit.seed_gaussian_mixture(8)),
    ]
    est, mixture = jaxmc.fit.chain(key, f, jaxmc.proposals.Grid(lo, hi), stages)
    ```

    Every round is an unbiased estimate (its density was fixed before it drew),
    so all rounds past each stage's warm-up are combined by
    `combine(parts, sequential=True)`, as in `adapt`. With `args`, `f` is called as `f(x, args)` (as in `adapt`).

    **Returns:** `(combined, proposal)`: the `Combined` of every stage's kept
    rounds (in order) and the last stage's proposal.
    """
    key = check_key(key)
    f = bind(check_callable(f), args)
    stages = list(stages)
    if not stages or not all(isinstance(s, Stage) for s in stages):
        raise TypeError("`stages` must be a non-empty sequence of jaxmc.fit.Stage.")
    if stages[0].seed is not None:
        raise ValueError("The first stage has no previous stage to seed it: its `seed` must be None.")
    integrand = Integrand(f, batched)
    kept = []
    samples = None
    for s, stage in enumerate(stages):
        iterations = check_count(stage.iterations, f"stages[{s}].iterations")
        n = check_count(stage.n_per_iteration, f"stages[{s}].n_per_iteration", minimum=2)
        warmup = check_count(stage.warmup, f"stages[{s}].warmup", minimum=0)
        if warmup >= iterations:
            raise ValueError(f"`stages[{s}].warmup` must be < its iterations = {iterations}.")
        if stage.seed is not None:
            proposal = stage.seed(proposal, samples)
        proposal = check_proposal(proposal, f"proposal of stage {s}", ("sample", "log_pdf"))
        seeds_next = s + 1 < len(stages) and stages[s + 1].seed is not None
        parts, state, samples = _compiled_adaptation(
            stage.rule, jax.random.fold_in(key, s), integrand, proposal, iterations, n,
            keep_samples=seeds_next,
        )
        proposal = stage.rule.proposal(state)
        kept.append(jax.tree.map(lambda a: a[warmup:], parts))
    parts = jax.tree.map(lambda *a: jnp.concatenate(a), *kept)
    return _warn_if_rounds_disagree(combine(parts, sequential=True)), proposal
