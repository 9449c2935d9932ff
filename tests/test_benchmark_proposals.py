"""The proposals benchmark's SciPy anchor draws the mixture jaxmc draws, with its density."""

import jax
import numpy as np

from benchmarks import proposals


def test_scipy_anchor_samples_the_same_mixture():
    with jax.enable_x64(True):
        gm, _, _ = proposals._proposals(3)
        x, p = proposals._scipy_sample(np.random.default_rng(0), gm, 4096)
        # SciPy's density of its points is jaxmc's: the same truncated components and weights.
        np.testing.assert_allclose(p, np.asarray(gm.pdf(x)), rtol=1e-10)
        # ...and its points agree with jaxmc's draws: each coordinate's mean over 4096 of
        # each within 5 standard errors of the difference.
        jx, _ = gm.sample(jax.random.key(1), 4096)
        jx = np.asarray(jx)
        se = np.sqrt(x.var(axis=0) / len(x) + jx.var(axis=0) / len(jx))
        assert np.all(np.abs(x.mean(axis=0) - jx.mean(axis=0)) < 5 * se)
