r"""The grid's held-out outlook on the early look of `integrate(method="auto")`'s QMC pilot.

`grid_outlook` fits VEGAS's product density to the nets' values and reads it on the same
points. On a sparse $f$ that flatters it without bound: the 8-D half-space indicator at
$10^5$ (volume 1/25) puts about 40 of the early look's 1,024 points inside, each alone in
its bins of most axes, so the density fitted to them fits them, and the outlook read 0 on 6
keys of 8. Nothing then dropped the grid before it was screened (`_auto`), 3 VEGAS+ rounds
measured 14-21 per evaluation against QMC's 0.8-7.7, and the stream had 5 nets of $2^{14}$.

Held out, the density is fitted to half of the replicas and read on the other half, both
ways (`held_out_outlook`). Where a product density fitted so does no better than the
uniform one, its relative variance per evaluation at least plain Monte Carlo's on the same
points, the grid is not trained (`held_out_drops_grid`). On the early look (1e5, 8 keys of
every `auto` benchmark case; 1e6, 4 keys) that held on the 8-D half-space, the oblique
resonances, the annulus, the 3-D ball, i-flow's 4-D camel and Genz's 8- and 16-D
oscillatory and discontinuous families, and QMC won every one of those runs as before; never
where a grid, QMC through it or a mixture seeded from it won (two Gaussians on the 4-D
diagonal, whose whole nets read 107-402 against plain MC's 130, decide blind or on their
power-law tail). Out of sample, the half-space's whole nets read 174-39,000 (in-sample
1.5-1.9). Over the suite's 20 keys at 1e5 and 1e6 only the half-space, the 4-D resonance,
the 4-D camel and Genz's 8- and 16-D discontinuous family at 1e5 changed estimates (the
stream now has 3 nets of $2^{15}$; RMS relative error 6.9e-3 -> 5.4e-3, 1.49e-2 -> 1.42e-2,
2.3e-4 -> 1.9e-4, 2.67e-4 -> 2.60e-4 and 2.41e-4 -> 2.66e-4); at 1e6 the stream is the
same and the rounds are skipped (the half-space's median call 18 -> 10 ms).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from ._pilot_nets import QMCFigures, outlook_read, outlook_values, product_log_density


def held_out_outlook(bins, y) -> jax.Array:
    r"""`grid_outlook` held out: VEGAS's product density fitted (`product_log_density`) to the
    values `y` `(R, m, ...)` of the first half of the `R` replicas, in `bins` `(R, m, d)`
    (`net_values`), its relative variance per evaluation read on the second half
    (`outlook_read`), and the same with the halves swapped; the mean of the two. Not clipped
    at 0 (read on other points, it may fall below). 0 in one dimension, where a grid is any
    piecewise-constant density."""
    if bins.shape[-1] == 1:
        return jnp.zeros((), y.dtype)
    index, values, square = outlook_values(bins, y)
    split = y.shape[0] // 2 * y.shape[1]  # the first half's points, replica by replica
    a, b = slice(0, split), slice(split, None)

    def read(fit, on):  # the density fitted on one half, read on the other
        log_q = product_log_density(index[fit], square[fit])
        return outlook_read(log_q, index[on], values[on], square[on])

    return (read(a, b) + read(b, a)) / 2


def held_out_drops_grid(qmc: QMCFigures, bins, y) -> jax.Array:
    """Whether the grid is not trained at all: a product density held out on the values `y`
    in `bins` (`held_out_outlook`) does no better than uniform sampling, at least plain MC's
    relative variance per evaluation (`qmc.plain`) on the same points, with QMC's exemptions
    from `outlook_drops_grid`: values that missed the integrand or few effective points
    (blind), a power-law tail that does not reach a cap, a product of one-dimensional factors."""
    held_out = held_out_outlook(bins, y)
    useless = (held_out >= qmc.plain) & (held_out > 0)
    return useless & ~qmc.blind & ~(qmc.heavy & ~qmc.capped) & ~qmc.separable
