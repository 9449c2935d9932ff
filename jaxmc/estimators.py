"""Monte Carlo estimators; each returns a `jaxmc.stats.Estimate`.

| function | estimator |
| --- | --- |
| `uniform` | basic estimator over a box, eq. 8 |
| `importance` | $\\frac1n\\sum f(X_i)/p(X_i)$, eq. 10/12 |
| `stratified` | $\\sum_k v_k F_k$ over a grid of strata, §4.2 |
| `randomized_qmc` | replicas of a randomised point set, variance from their spread |
| `mis`, `mis_one_sample` | multiple importance sampling, balance or power heuristic |
| `control_variate`, `antithetic` | classic variance reduction for the uniform estimator |
| `integrate` | streaming driver with tolerances, chunks and devices; `method="auto"` picks by a pilot (`IntegrationEstimate`, `Pilot`) |
"""

from ._auto._pilot import Pilot as Pilot
from ._estimators._basic import importance as importance, uniform as uniform
from ._estimators._control import antithetic as antithetic, control_variate as control_variate
from ._estimators._integrate import (
    IntegrationEstimate as IntegrationEstimate,
    integrate as integrate,
)
from ._estimators._mis import mis as mis, mis_one_sample as mis_one_sample
from ._estimators._qmc import QMCEstimate as QMCEstimate, randomized_qmc as randomized_qmc
from ._estimators._stratified import stratified as stratified


__all__ = [
    "IntegrationEstimate",
    "Pilot",
    "QMCEstimate",
    "antithetic",
    "control_variate",
    "importance",
    "integrate",
    "mis",
    "mis_one_sample",
    "randomized_qmc",
    "stratified",
    "uniform",
]
