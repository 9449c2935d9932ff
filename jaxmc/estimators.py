"""Monte Carlo estimators; each returns a `jaxmc.stats.Estimate`.

| function | estimator |
| --- | --- |
| `uniform` | basic estimator over a box, eq. 8 |
| `importance` | $\\frac1n\\sum f(X_i)/p(X_i)$, eq. 10/12 |
| `integrate` | streaming driver with tolerances, chunks and devices |
"""

from ._estimators._basic import importance as importance, uniform as uniform
from ._estimators._integrate import integrate as integrate


__all__ = ["importance", "integrate", "uniform"]
