"""jaxmc: Monte Carlo integration in JAX."""

import importlib.metadata as _metadata

from . import (
    distributions as distributions,
    estimators as estimators,
    fit as fit,
    methods as methods,
    points as points,
    proposals as proposals,
    quad as quad,
    render as render,
    stats as stats,
    testing as testing,
    warps as warps,
)
from ._expectation import Expectation as Expectation, expectation as expectation
from .estimators import (
    IntegrationEstimate as IntegrationEstimate,
    antithetic as antithetic,
    control_variate as control_variate,
    importance as importance,
    integrate as integrate,
    mis as mis,
    mis_one_sample as mis_one_sample,
    randomized_qmc as randomized_qmc,
    stratified as stratified,
    uniform as uniform,
)
from .stats import (
    Combined as Combined,
    Estimate as Estimate,
    ReliabilityWarning as ReliabilityWarning,
    combine as combine,
)


__version__ = _metadata.version("jaxmc")

__all__ = [
    "Combined",
    "Estimate",
    "Expectation",
    "IntegrationEstimate",
    "ReliabilityWarning",
    "antithetic",
    "combine",
    "control_variate",
    "distributions",
    "estimators",
    "expectation",
    "fit",
    "importance",
    "integrate",
    "methods",
    "mis",
    "mis_one_sample",
    "points",
    "proposals",
    "quad",
    "randomized_qmc",
    "render",
    "stats",
    "stratified",
    "testing",
    "uniform",
    "warps",
]
