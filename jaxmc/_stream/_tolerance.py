r"""`integrate`'s tolerances: checking them, and saying why one was not met.

A run with `rtol`/`atol` stops once its standard error is at most
$\max(\mathrm{atol}, \mathrm{rtol}\,|\bar I|)$, or at its budget. The error bar never
falls below the rounding floor of the dtype's arithmetic
(`jaxmc.stats.rounding_floor`: $4\varepsilon$ times the mean absolute contribution), so
an `rtol` below that fraction is refused up front, and an `atol` below it (which depends
on the integral, unknown before the run) stops the stream when its error bar reaches the
floor (`_stream.at_rounding_floor`), with a warning that says so.
"""
from __future__ import annotations

from typing import Any

import jax
import numpy as np

from .._checks import as_real_array, is_concrete
from .._stats import Estimate, rounding_floor


def check_tolerance(tol: Any, name: str, dtype: Any) -> Any:
    """A tolerance: one real scalar >= 0 (checked in value when concrete). A relative
    tolerance below the rounding floor of the integration `dtype` cannot be met."""
    if tol is None:
        return None
    if isinstance(tol, (bool, np.bool_)):
        raise TypeError(f"`{name}` must be a real number, got {tol!r}.")
    value = as_real_array(tol, f"`{name}` must be a real number")
    if value.shape != ():
        raise ValueError(
            f"`{name}` must be a scalar (one tolerance for every component), got shape {value.shape}."
        )
    if is_concrete(tol):  # (under jit, `value` may be staged even for a Python float)
        value = float(np.asarray(tol))
        if not np.isfinite(value) or value < 0:
            raise ValueError(f"`{name}` must be a finite number >= 0, got {value!r}.")
        if name == "rtol" and 0 < value < rounding_floor(dtype):
            floor = rounding_floor(dtype)
            raise ValueError(
                f"`rtol`={value:g} is below what {np.dtype(dtype).name} arithmetic can deliver: "
                f"the rounding error of the mean is about {floor:.1e} of its magnitude; "
                f"{_higher_precision(dtype, f'use rtol >= {floor:.1e}')}."
            )
    return tol


def _higher_precision(dtype: Any, or_else: str) -> str:
    """How to integrate in float64 instead of `dtype`, or `or_else`."""
    if np.dtype(dtype) == np.float64:
        return or_else
    x64 = 'jax.config.update("jax_enable_x64", True)'
    how = "pass float64 bounds `lo`, `hi` (float64 is on)" if jax.config.jax_enable_x64 else x64
    return f"integrate in float64 ({how}), or {or_else}"


def unmet_tolerance(est: Estimate, budget: int, rtol, atol, dtype: Any) -> str:
    """The warning of a run that did not meet its tolerance: at the rounding floor of
    `dtype` (no budget meets it), or within `budget` evaluations."""
    mean, stderr = np.asarray(est.mean), np.asarray(est.stderr)
    unmet = stderr > np.maximum(np.asarray(atol), np.asarray(rtol) * np.abs(mean))
    floor = rounding_floor(dtype)
    # At the floor the error bar is `floor` times the mean absolute contribution: |mean| for
    # an integrand of one sign. Whatever the sign, only the floor stops a run short of its
    # budget unmet (an exhausted budget leaves unspent only what its last nets, rounds or the
    # pilot's skipped stages could not use: far less than half).
    at_floor = np.any(unmet & (stderr <= 1.01 * floor * np.abs(mean))) or int(est.n) < budget // 2
    if at_floor:
        reached = np.max(np.where(unmet, stderr, 0.0))
        return (
            f"integrate: the standard error reached the rounding floor of {np.dtype(dtype).name} "
            f"arithmetic (about {floor:.1e} of the mean |f/p|) after {int(est.n):,} "
            f"evaluations, unmet (mean {mean}, stderr {stderr}); no budget meets the tolerance: "
            f"{_higher_precision(dtype, f'ask for a standard error of at least {reached:.1e}')}"
            " (`atol`, or `rtol` times |mean|)."
        )
    return (
        f"integrate: the tolerance was not met within the budget of {budget:,} evaluations "
        f"(mean {mean}, stderr {stderr}); raise `max_n`/`n`, or relax `rtol`/`atol`."
    )
