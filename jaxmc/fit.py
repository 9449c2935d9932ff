r"""Importance densities fitted to an integrand: `fit`, `fit_on_samples`, `adapt`.

`fit` minimises the importance estimator's variance over a proposal's
parameters with an optimistix minimiser; `adapt` is the VEGAS-style loop
(sample, estimate, refit, combine the iterations), traced end to end so it
jits and vmaps.
"""

from ._fit._adapt import adapt as adapt
from ._fit._fit import (
    OBJECTIVES as OBJECTIVES,
    FitResult as FitResult,
    fit as fit,
    fit_on_samples as fit_on_samples,
    parameter_spec as parameter_spec,
)
