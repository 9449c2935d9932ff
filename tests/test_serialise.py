"""Fitted densities are data: `eqx.tree_serialise_leaves` saves a proposal and
`eqx.tree_deserialise_leaves` restores it into a freshly built one of the same structure."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmc.proposals import (
    Flow,
    GaussianMixture,
    Grid,
    Mixture,
    Partition,
    PiecewiseLinear,
    Uniform,
)


LO, HI = jnp.array([0.0, -1.0]), jnp.array([1.0, 2.0])


def _perturbed(seed, proposal, scale=0.3):
    """Every floating-point parameter moved off its initial value (as a fit would); the
    noise comes from numpy, so perturbing costs no compilation beyond one add per shape."""
    rng = np.random.default_rng(seed)
    return jax.tree.map(
        lambda leaf: (
            leaf + jnp.asarray(scale * rng.standard_normal(leaf.shape), leaf.dtype)
            if eqx.is_inexact_array(leaf)
            else leaf
        ),
        proposal,
    )


# Each case: (the fitted or adapted density, a fresh `like` built as a user would rebuild it).
def _grid(key):
    # `adapt` (VEGAS or VEGAS+) refines the Grid's `logits`; VEGAS+'s stratification lives
    # in the rule's state, not in the density, and is not saved.
    return _perturbed(1, Grid(LO, HI, bins=16)), Grid(LO, HI, bins=16)


def _partition(key):
    # The tree is integer arrays. Two cuts, as `adapt` makes them (the layout is in
    # `Partition`'s docstring): the box halved along axis 0 into nodes 1 and 2, then
    # node 2 halved along axis 1 into nodes 3 and 4.
    like = Partition(LO, HI, 4)
    grown = eqx.tree_at(
        lambda p: (p.child, p.axis, p.corner, p.level, p.size),
        like,
        (
            like.child.at[0].set(1).at[2].set(3),
            like.axis.at[2].set(1),
            like.corner.at[2, 0].set(1).at[3, 0].set(1).at[4].set(1),
            like.level.at[1:3, 0].set(1).at[3:5].set(1),
            jnp.array(5, jnp.int32),
        ),
    )
    logits = jax.random.normal(key, grown.logits.shape, grown.logits.dtype)
    return eqx.tree_at(lambda p: p.logits, grown, logits), like


def _uniform(key):
    return Uniform(LO, HI), Uniform(jnp.zeros(2), jnp.ones(2))


def _gaussian_mixture(key):
    return (
        _perturbed(2, GaussianMixture(key, LO, HI, components=3)),
        GaussianMixture(jax.random.key(0), LO, HI, components=3),
    )


def _piecewise_linear(key):
    return _perturbed(3, PiecewiseLinear(LO, HI, bins=4)), PiecewiseLinear(LO, HI, bins=4)


def _flow(key):
    options = dict(layers=1, bins=4, hidden=4, depth=1)
    return (
        _perturbed(4, Flow(key, LO, HI, **options), scale=0.1),
        Flow(jax.random.key(0), LO, HI, **options),
    )


def _mixture(key):
    # A fitted density with a defensive uniform share, weights trained too.
    fitted = Mixture(
        (PiecewiseLinear(LO, HI, bins=3), Uniform(LO, HI)), (0.8, 0.2), train_weights=True
    )
    like = Mixture((PiecewiseLinear(LO, HI, bins=3), Uniform(LO, HI)), train_weights=True)
    return _perturbed(5, fitted), like


CASES = {
    "Uniform": _uniform,
    "Grid": _grid,
    "Partition": _partition,
    "GaussianMixture": _gaussian_mixture,
    "PiecewiseLinear": _piecewise_linear,
    "Flow": _flow,
    "Mixture": _mixture,
}


@eqx.filter_jit
def _draw(proposal, key):
    x, p = proposal.sample(key, 64)
    return x, p, proposal.pdf(x)


def _leaves(tree):
    return jax.tree.leaves(eqx.filter(tree, eqx.is_array))


@pytest.mark.parametrize("name", list(CASES))
def test_restored_density_is_the_saved_one(name, key, tmp_path):
    fitted, like = CASES[name](key)
    # The fresh `like` is another density (for `Uniform`, another box): restoring has
    # something to do.
    assert not all(
        np.array_equal(a, b) for a, b in zip(_leaves(like), _leaves(fitted), strict=True)
    )
    path = tmp_path / "density.eqx"
    eqx.tree_serialise_leaves(path, fitted)
    restored = eqx.tree_deserialise_leaves(path, like)

    assert type(restored) is type(fitted)
    assert jax.tree.structure(restored) == jax.tree.structure(fitted)
    for a, b in zip(_leaves(restored), _leaves(fitted), strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(a, b)

    draw_key = jax.random.fold_in(key, 1)
    for a, b in zip(_draw(restored, draw_key), _draw(fitted, draw_key), strict=True):
        np.testing.assert_array_equal(a, b)  # bit-identical samples and densities
