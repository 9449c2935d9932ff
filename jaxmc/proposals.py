r"""Parametric, differentiable importance densities on a box $[lo, hi]$.

A *proposal* is any object with `sample(key, n) -> (x, pdf)` and `pdf(x)` (and
`log_pdf(x)`). `x` has shape `(n, d)` for `(d,)` bounds, or `(n,)` for scalar
bounds; `pdf` takes a batch `(n, d) -> (n,)` or one point `(d,) -> ()`.
jaxmc's proposals are equinox Modules (pytrees), so they pass through `jit`
and their array fields are the parameters `fit` optimises.

| density | what it is |
| --- | --- |
| `Uniform` | $1/\mathrm{vol}$ on the box |
| `GaussianMixture` | diagonal Gaussians truncated to the box; `from_samples` fits one by EM |
| `Grid` | VEGAS's separable piecewise-constant map, refined by `Grid.refine` |
| `PiecewiseLinear` | a separable piecewise-linear density |
| `Partition` | piecewise constant on an adaptive kd-tree of cells |
| `Flow` | coupling layers of rational-quadratic splines (neural importance sampling) |
| `Mixture` | $\sum_k w_k p_k$, e.g. a fitted density with a defensive `Uniform` share |

The contract every consumer relies on is `AbstractProposal` (`sample`,
`log_pdf`, `pdf`, `weighted_draw`); `AbstractUnitMap` is the base of the
densities that map the unit cube with a Jacobian (`Grid`, `PiecewiseLinear`,
`Flow`).

A fitted density is data: `eqx.tree_serialise_leaves(path, proposal)` saves
its arrays and `eqx.tree_deserialise_leaves(path, like)` restores them into
`like`, a freshly built proposal of the same structure (same type, box shape
and sizes, e.g. `Grid(lo, hi, bins)`); the restored density draws the same
samples with the same pdf for the same key.
"""

from ._proposals._base import (
    AbstractProposal as AbstractProposal,
    AbstractUnitMap as AbstractUnitMap,
    check_proposal as check_proposal,
    weighted_draw as weighted_draw,
)
from ._proposals._flow import Flow as Flow
from ._proposals._gaussian_mixture import GaussianMixture as GaussianMixture
from ._proposals._grid import Grid as Grid
from ._proposals._mixture import Mixture as Mixture
from ._proposals._partition import Partition as Partition
from ._proposals._piecewise_linear import PiecewiseLinear as PiecewiseLinear
from ._proposals._uniform import Uniform as Uniform


__all__ = [
    "AbstractProposal",
    "AbstractUnitMap",
    "Flow",
    "GaussianMixture",
    "Grid",
    "Mixture",
    "Partition",
    "PiecewiseLinear",
    "Uniform",
    "check_proposal",
    "weighted_draw",
]
