"""Adaptation rules as objects: `adapt` over any rule, custom rules, `chain` and its seeds."""

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.scipy.special import erf

import jaxmc
from jaxmc._stats import estimate_iid
from jaxmc.fit import (
    AbstractAdaptation,
    Integrand,
    PartitionGrowth,
    Refit,
    Samples,
    Stage,
    Vegas,
    VegasPlus,
    adapt,
    chain,
    run_adaptation,
    seed_gaussian_mixture,
)
from jaxmc.proposals import GaussianMixture, Grid, Partition


D = 3
LO, HI = jnp.zeros(D), jnp.ones(D)
CENTRES = (0.3, 0.7)
WIDTH = 0.05


def two_peaks(x):
    """Two Gaussian peaks on the diagonal of the unit cube, weights 1 and 1/2."""
    g = lambda c: jnp.exp(-jnp.sum((x - c) ** 2) / (2 * WIDTH**2))
    return g(CENTRES[0]) + 0.5 * g(CENTRES[1])


def two_peaks_integral():
    def axis(c):
        return WIDTH * np.sqrt(np.pi / 2) * float(erf((1 - c) / (WIDTH * np.sqrt(2))) + erf(c / (WIDTH * np.sqrt(2))))

    return axis(CENTRES[0]) ** D + 0.5 * axis(CENTRES[1]) ** D


def combined_arrays(result):
    est, prop = result
    return jax.tree.leaves((est.mean, est.variance, est.parts.mean, eqx.filter(prop, eqx.is_array)))


@pytest.mark.parametrize(
    "options, rule",
    [
        ({"stratify": False}, Vegas()),
        ({}, VegasPlus()),
        ({"stratify": True, "beta": 0.5}, VegasPlus(beta=0.5)),
    ],
)
def test_options_and_rule_objects_agree_exactly(key, options, rule):
    """`adapt`'s options only choose a rule: passing the rule itself gives the same numbers."""
    grid = Grid(LO, HI, 16)
    a = adapt(key, two_peaks, grid, iterations=3, n_per_iteration=2000, **options)
    b = adapt(key, two_peaks, grid, iterations=3, n_per_iteration=2000, rule=rule)
    for x, y in zip(combined_arrays(a), combined_arrays(b), strict=True):
        np.testing.assert_array_equal(x, y)


# Rule mechanics on sparse rounds of narrow peaks: the diagnostics rightly warn there.
@pytest.mark.filterwarnings("ignore::jaxmc.ReliabilityWarning")
def test_partition_rule_object(key):
    part = Partition(LO[:2], HI[:2], 32)
    f = lambda x: two_peaks(jnp.concatenate([x, jnp.full((1,), 0.3)]))
    a = adapt(key, f, part, iterations=2, n_per_iteration=256, passes=2)
    b = adapt(key, f, part, iterations=2, n_per_iteration=256, rule=PartitionGrowth(passes=2))
    for x, y in zip(combined_arrays(a), combined_arrays(b), strict=True):
        np.testing.assert_array_equal(x, y)


class FrozenState(eqx.Module):
    proposal: object
    n: int = eqx.field(static=True)


class Frozen(AbstractAdaptation):
    """A rule that adapts nothing: i.i.d. rounds from a fixed proposal (a user's own rule)."""

    def init(self, key, proposal, n):
        return FrozenState(proposal, n)

    def step(self, key, index, state, integrand):
        n = state.n
        x, px = state.proposal.sample(jax.random.fold_in(key, index), n)
        fx = integrand(x)
        est = estimate_iid(fx / px, jnp.zeros((n,), bool))
        return state, est, Samples(x, fx, jnp.log(px), jnp.full((n,), 1.0 / n))

    def proposal(self, state):
        return state.proposal


@pytest.mark.filterwarnings("ignore::jaxmc.ReliabilityWarning")  # a broad frozen mixture
def test_a_new_rule_is_a_new_class(key):
    """A user's rule runs through `adapt` unchanged: unbiased rounds, the proposal kept."""
    gm = GaussianMixture(jax.random.key(3), LO, HI, 2, scale=0.2)
    est, prop = adapt(key, two_peaks, gm, iterations=6, n_per_iteration=4000, rule=Frozen())
    assert est.parts.mean.shape == (6,)
    assert abs(float(est.mean) - two_peaks_integral()) < 5 * float(est.stderr)
    for x, y in zip(jax.tree.leaves(gm), jax.tree.leaves(prop), strict=True):
        np.testing.assert_array_equal(x, y)
    # Under jit, with the rule closed over.
    est_jit, _ = jax.jit(
        lambda k: adapt(k, two_peaks, gm, iterations=6, n_per_iteration=4000, rule=Frozen())
    )(key)
    np.testing.assert_allclose(est_jit.mean, est.mean, rtol=1e-12)


@pytest.mark.parametrize(
    "rule, proposal, n",
    [
        (Vegas(), Grid(LO, HI, 16), 1000),
        (VegasPlus(), Grid(LO, HI, 16), 1000),
        (PartitionGrowth(), Partition(LO, HI, 64), 1000),
        (Refit(steps=2), GaussianMixture(jax.random.key(2), LO, HI, 2), 500),
    ],
)
def test_samples_reproduce_the_round_estimate(key, rule, proposal, n):
    r"""The last round's `Samples` follow their convention: $\sum_i w_i f(x_i)/q(x_i)$ is that
    round's estimate, for i.i.d. and stratified rules alike."""
    parts, state, s = run_adaptation(
        rule, key, Integrand(two_peaks), proposal, 2, n, keep_samples=True
    )
    assert type(rule.proposal(state)) is type(proposal)
    assert s.x.shape == (n, D) and s.weights.shape == (n,)
    np.testing.assert_allclose(float(jnp.sum(s.weights)), 1.0, rtol=1e-12)
    total = jnp.sum(s.weights * s.fx * jnp.exp(-s.log_q))
    np.testing.assert_allclose(float(total), float(parts.mean[-1]), rtol=1e-10)


@pytest.mark.parametrize("keep_samples", [False, True])
def test_active_rounds_are_the_first_rounds_of_a_shorter_run(key, keep_samples):
    """`active=k` of 5 rounds runs exactly the rounds of `iterations=k` (same keys, state
    and kept samples) and estimates zeros for the skipped ones, under one compiled program
    for every k, none included."""
    run = eqx.filter_jit(
        lambda active: run_adaptation(VegasPlus(), key, Integrand(two_peaks), Grid(LO, HI, 16),
                                         5, 512, keep_samples=keep_samples, active=active)
    )
    # (The reference runs compiled too: eagerly, its setup dispatches op by op.)
    reference = eqx.filter_jit(run_adaptation)
    for k in (2, 4):
        parts, state, samples = run(jnp.int32(k))
        ref_parts, ref_state, ref_samples = reference(
            VegasPlus(), key, Integrand(two_peaks), Grid(LO, HI, 16), k, 512,
            keep_samples=keep_samples,
        )
        np.testing.assert_array_equal(parts.mean[:k], ref_parts.mean)
        assert np.all(np.asarray(parts.mean[k:]) == 0)
        np.testing.assert_array_equal(state.grid.logits, ref_state.grid.logits)
        if keep_samples:
            np.testing.assert_array_equal(samples.x, ref_samples.x)
    # None active: no round runs, the grid stays as it started.
    parts, state, _ = run(jnp.int32(0))
    assert np.all(np.asarray(parts.mean) == 0)
    np.testing.assert_array_equal(state.grid.logits, Grid(LO, HI, 16).logits)


def test_vegas_plus_rounds_without_diagnostics(key):
    """`VegasPlus(diagnostics=False)` runs the same rounds (grids, means, effective sample
    sizes) and skips only the search for the largest values: k-hat is NaN and a power-law
    tail no longer raises a round's variance to its i.i.d. bound."""
    singular = lambda x: jnp.prod(x**-0.4)  # noqa: E731  (a power-law tail, k = 0.4 per axis)
    runs = [run_adaptation(VegasPlus(diagnostics=flag), key, Integrand(singular), Grid(LO, HI, 16),
                           4, 2048)
            for flag in (True, False)]
    (parts, state, _), (quick, quick_state, _) = runs
    np.testing.assert_array_equal(quick.mean, parts.mean)
    np.testing.assert_array_equal(quick_state.grid.logits, state.grid.logits)
    np.testing.assert_allclose(quick.ess, parts.ess, rtol=1e-5)
    assert np.all(np.isnan(quick.pareto_k)) and np.all(np.asarray(parts.pareto_k) > 0.2)
    assert np.all(np.asarray(quick.variance) <= np.asarray(parts.variance))
    assert np.any(np.asarray(quick.variance) < np.asarray(parts.variance))  # the bound acted


def test_coarse_vegas_plus_runs_the_coarse_grid_held_in_more_bins(key):
    """`VegasPlus(coarse_bins=M, coarse=True)` on a grid of 4M bins runs the rounds of a grid
    of M bins (the same map, so the same points, means and edges at every fourth), with
    `coarse` traced or not; `coarse=False` refines all 4M; `M` must divide the bins."""
    rounds = lambda rule, bins: run_adaptation(  # noqa: E731
        rule, key, Integrand(two_peaks), Grid(LO, HI, bins), 4, 1024)
    parts, state, _ = rounds(VegasPlus(), 16)
    held, held_state, _ = rounds(VegasPlus(coarse_bins=16, coarse=True), 64)
    np.testing.assert_allclose(held.mean, parts.mean, rtol=1e-12)
    np.testing.assert_allclose(held_state.grid.edges[:, ::4], state.grid.edges, atol=1e-12)
    widths = np.reshape(np.diff(np.asarray(held_state.grid.edges)), (D, 16, 4))
    np.testing.assert_allclose(widths, widths[..., :1] * np.ones(4), rtol=1e-9)  # split evenly
    traced = eqx.filter_jit(lambda flag: rounds(VegasPlus(coarse_bins=16, coarse=flag), 64))
    for flag, (expected, expected_state) in ((True, (held, held_state)),
                                             (False, rounds(VegasPlus(), 64)[:2])):
        got, got_state, _ = traced(jnp.asarray(flag))
        np.testing.assert_allclose(got.mean, expected.mean, rtol=1e-12)
        np.testing.assert_allclose(got_state.grid.logits, expected_state.grid.logits, atol=1e-9)
        assert bool(got_state.coarse) == flag
    with pytest.raises(ValueError, match="coarse_bins"):
        rounds(VegasPlus(coarse_bins=24, coarse=True), 64)


def test_vegas_plus_refines_on_each_bins_mean(key):
    r"""A VEGAS+ round refines on each bin's weighted mean of $(f/p)^2$, not its sum: where
    $f/p$ is flat the grid stays put whatever the number of points in each bin, and a fine
    grid trained on $\prod_i x_i^{-1/3}$ in 6-D as `integrate` trains it (256 bins, then
    split 4x and refined) samples it with i.i.d. relative variance ~0.0075 (3 keys
    0.0071-0.0080; vegas's map after its run, 0.006). Summed, the counts' noise, with 1% of
    the bins held as the defensive share, left it at 0.019-0.021."""
    grid = Grid(LO, HI, 64)
    state = VegasPlus().init(key, grid, 4096)
    flat = VegasPlus().step(key, 0, state, Integrand(lambda x: jnp.float64(2.0)))[0].grid
    np.testing.assert_allclose(flat.edges, grid.edges, atol=1e-12)

    d = 6
    f = lambda x: jnp.prod(x ** (-1 / 3)) * (2 / 3) ** d  # noqa: E731 (integral 1)
    with warnings.catch_warnings():  # (the rounds' error bars may warn of the tail)
        warnings.simplefilter("ignore", jaxmc.ReliabilityWarning)
        _, grid = adapt(key, f, Grid(jnp.zeros(d), jnp.ones(d), 256), iterations=10,
                        n_per_iteration=2048)
        _, grid = adapt(jax.random.fold_in(key, 1), f, grid.subdivided(4), iterations=8,
                        n_per_iteration=8192)
    x, log_q = grid.map(jax.random.uniform(jax.random.fold_in(key, 2), (100_000, d)))
    w = jax.vmap(f)(x) / jnp.exp(log_q)
    assert float(jnp.var(w) / jnp.mean(w) ** 2) < 0.011


def test_chain_seeds_a_mixture_from_the_grid(key):
    """VEGAS+ finds the peaks; a mixture seeded from its weighted samples puts a component on
    each, is refitted, and the combined estimate of every kept round is unbiased and beats the
    grid's own rounds."""
    stages = [
        Stage(VegasPlus(), iterations=5, n_per_iteration=8000, warmup=2),
        Stage(Refit(steps=8), iterations=3, n_per_iteration=8000, seed=seed_gaussian_mixture(4)),
    ]
    est, gm = chain(key, two_peaks, Grid(LO, HI, 32), stages)
    assert isinstance(gm, GaussianMixture)
    assert est.parts.mean.shape == (3 + 3,)
    truth = two_peaks_integral()
    assert abs(float(est.mean) - truth) < 5 * float(est.stderr)
    grid_rounds, gm_rounds = est.parts.variance[:3], est.parts.variance[3:]
    assert float(jnp.max(gm_rounds)) < float(jnp.min(grid_rounds))
    # A heavy component sits on each peak.
    weights = jax.nn.softmax(gm.logits)
    for c in CENTRES:
        near = jnp.all(jnp.abs(gm.means - c) < 2 * WIDTH, axis=-1)
        assert float(jnp.sum(jnp.where(near, weights, 0.0))) > 0.1


def test_chain_single_stage_is_adapt_with_a_folded_key(key):
    grid = Grid(LO, HI, 16)
    a = chain(key, two_peaks, grid, [Stage(Vegas(), iterations=3, n_per_iteration=1000)])
    b = adapt(
        jax.random.fold_in(key, 0), two_peaks, grid, iterations=3, n_per_iteration=1000,
        stratify=False,
    )
    for x, y in zip(combined_arrays(a), combined_arrays(b), strict=True):
        np.testing.assert_array_equal(x, y)


def test_rule_errors(key):
    gm = GaussianMixture(jax.random.key(0), LO, HI, 2)
    with pytest.raises(ValueError, match="Grid"):
        adapt(key, two_peaks, gm, iterations=2, n_per_iteration=64, rule=Vegas())
    with pytest.raises(ValueError, match="Partition"):
        adapt(key, two_peaks, Grid(LO, HI), iterations=2, n_per_iteration=64, rule=PartitionGrowth())
    with pytest.raises(TypeError, match="rule"):
        adapt(key, two_peaks, gm, iterations=2, n_per_iteration=64, rule="vegas")
    with pytest.raises(ValueError, match="seed"):
        chain(key, two_peaks, gm, [Stage(Refit(), 2, 64, seed=seed_gaussian_mixture(2))])
    with pytest.raises(TypeError, match="stages"):
        chain(key, two_peaks, gm, [])
    with pytest.raises(ValueError, match="warmup"):
        chain(key, two_peaks, Grid(LO, HI), [Stage(Vegas(), 2, 64, warmup=2)])
    with pytest.raises(ValueError, match="objective"):
        adapt(key, two_peaks, gm, iterations=2, n_per_iteration=64, rule=Refit(objective="x"))


def test_public_namespace_of_fit():
    """The rules and the chaining API are public; nothing private leaks."""
    for name in jaxmc.fit.__all__:
        assert not name.startswith("_") and hasattr(jaxmc.fit, name)
