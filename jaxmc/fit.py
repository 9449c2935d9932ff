r"""Importance densities fitted to an integrand: `fit`, `fit_on_samples`, `adapt`, `chain`.

`fit` minimises the importance estimator's variance over a proposal's
parameters with an optimistix minimiser. `adapt` runs rounds of an adaptation
rule — sample, estimate, adapt — and combines them (vegas's loop), traced end
to end so it jits and vmaps. The rules are objects (`AbstractAdaptation`):

| rule | adapts | how |
| --- | --- | --- |
| `Vegas` | `Grid` | VEGAS grid refinement on $(f/p)^2$ |
| `VegasPlus` | `Grid` | VEGAS refinement plus adaptive stratification of the map's cube |
| `PartitionGrowth` | `Partition` | MISER-like stratified sampling and cell splitting |
| `Refit` | any proposal | optimistix refitting on each round's samples |

`chain` runs `Stage`s one after another, each optionally seeded from the
previous stage's weighted `Samples` (e.g. `seed_gaussian_mixture`).
"""

from ._fit._adapt import (
    Stage as Stage,
    adapt as adapt,
    chain as chain,
    default_rule as default_rule,
    seed_gaussian_mixture as seed_gaussian_mixture,
)
from ._fit._fit import FitResult as FitResult, fit as fit, fit_on_samples as fit_on_samples
from ._fit._miser import PartitionGrowth as PartitionGrowth
from ._fit._objectives import OBJECTIVES as OBJECTIVES
from ._fit._refit import Refit as Refit
from ._fit._rule import (
    AbstractAdaptation as AbstractAdaptation,
    Integrand as Integrand,
    Samples as Samples,
    run_adaptation as run_adaptation,
)
from ._fit._solvers import parameter_spec as parameter_spec
from ._fit._vegas import Vegas as Vegas, VegasPlus as VegasPlus


__all__ = [
    "OBJECTIVES",
    "AbstractAdaptation",
    "FitResult",
    "Integrand",
    "PartitionGrowth",
    "Refit",
    "Samples",
    "Stage",
    "Vegas",
    "VegasPlus",
    "adapt",
    "chain",
    "default_rule",
    "fit",
    "fit_on_samples",
    "parameter_spec",
    "run_adaptation",
    "seed_gaussian_mixture",
]
