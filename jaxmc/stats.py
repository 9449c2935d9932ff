r"""Estimates with error bars, their diagnostics and combination, and mergeable running moments.

An `Estimate` is what every estimator returns: the integral estimate, the
estimated variance *of that estimate* (for $n$ i.i.d. samples $\sigma^2/n$;
Owen, *Monte Carlo theory, methods and examples*, ch. 2), the evaluation counts, and
diagnostics of whether the error bar can be believed (`ess`, `n_nonzero`,
`pareto_k`; `unreliable` and `reliability_reasons` read them). `combine` merges
independent estimates by inverse-variance weights, as vegas does across its iterations.
The spread of a few replicas is an error bar with few degrees of freedom (`Estimate.dof`):
its intervals use Student's t (`student_t_quantile`). `Moments` are
the mergeable sufficient statistics `(count, mean, m2)` of a stream of values
(Chan, Golub and LeVeque's update: `moments`, `merge`, `merge_all`).
"""

from ._combine import Combined as Combined, combine as combine
from ._diagnostics import (
    ReliabilityWarning as ReliabilityWarning,
    reliability_reasons as reliability_reasons,
    rounding_floor as rounding_floor,
    unreliable as unreliable,
)
from ._stats import (
    Estimate as Estimate,
    Moments as Moments,
    merge as merge,
    merge_all as merge_all,
    moments as moments,
    student_t_quantile as student_t_quantile,
)


__all__ = [
    "Combined",
    "Estimate",
    "Moments",
    "ReliabilityWarning",
    "combine",
    "merge",
    "merge_all",
    "moments",
    "reliability_reasons",
    "rounding_floor",
    "student_t_quantile",
    "unreliable",
]
