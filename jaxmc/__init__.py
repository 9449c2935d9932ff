"""jaxmc: Monte Carlo integration in JAX."""

import importlib.metadata

from . import (
    estimators as estimators,
    points as points,
    proposals as proposals,
    quad as quad,
    stats as stats,
)
from .estimators import (
    importance as importance,
    integrate as integrate,
    uniform as uniform,
)
from .stats import Combined as Combined, Estimate as Estimate, combine as combine


__version__ = importlib.metadata.version("jaxmc")
