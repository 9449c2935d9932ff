"""Shared pieces of the benchmark suites: context, results, the timer and tables."""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
import statistics
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import jax
import numpy as np


@dataclasses.dataclass
class Context:
    """What a suite is given: the size setting and where to write files."""

    quick: bool
    out: Path

    def log(self, message: str) -> None:
        print(f"  {message}", file=sys.stderr, flush=True)


@dataclasses.dataclass
class Result:
    """What a suite returns: a markdown section and JSON-serialisable data."""

    markdown: str
    data: dict[str, Any]
    plots: list[str] = dataclasses.field(default_factory=list)


@dataclasses.dataclass(frozen=True)
class Timing:
    """Wall-clock seconds of the calls `time_call` made, the first one included.

    The first call of a jitted function compiles, so it is kept apart: `median_s`
    and `min_s` are over the further calls (over the first when there were none).
    """

    seconds: tuple[float, ...]
    output: Any = dataclasses.field(repr=False)  # what the last call returned

    @property
    def first_s(self) -> float:
        return self.seconds[0]

    @property
    def steady(self) -> tuple[float, ...]:
        return self.seconds[1:] or self.seconds

    @property
    def median_s(self) -> float:
        return statistics.median(self.steady)

    @property
    def min_s(self) -> float:
        return min(self.steady)

    def summary(self) -> dict[str, float]:
        """`first_s`, `median_s` and `min_s`, for a suite's JSON."""
        return {"first_s": self.first_s, "median_s": self.median_s, "min_s": self.min_s}


def time_call(fn: Callable[[], Any], *, repeats: int = 5) -> Timing:
    """Time `fn()` once, then `repeats` more times, each call ended with `block_until_ready`.

    The benchmarks' only timer. To time calls on different inputs (new keys, new
    seeds), let `fn` take the next one from an iterator.
    """
    seconds: list[float] = []
    output: Any = None
    for _ in range(1 + repeats):
        output = None  # let the previous output go before the next call
        start = time.perf_counter()
        output = jax.block_until_ready(fn())
        seconds.append(time.perf_counter() - start)
    return Timing(tuple(seconds), output)


# The event JAX records once per program compiled by XLA (its backend compilation).
_BACKEND_COMPILE = "/jax/core/compile/backend_compile_duration"


@contextlib.contextmanager
def compiled_programs() -> Iterator[list[float]]:
    """The seconds of each XLA compilation inside the block (its length: the programs
    compiled; a cache hit of the persistent compilation cache is none)."""
    seconds: list[float] = []

    def listener(event: str, duration: float, **_: Any) -> None:
        if event == _BACKEND_COMPILE:
            seconds.append(duration)

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield seconds
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


def normal_equivalent(absz, dofs) -> np.ndarray:
    """|z| = |error| / stderr of error bars with `dofs` degrees of freedom, as the standard
    normal |z| with the same two-sided tail (Student's t; unchanged for infinite `dofs`), so
    that |z| <= 2 is coverage by `Estimate.interval` at the level of 2 sigma. NaN covers nothing."""
    from scipy import stats

    absz = np.where(np.isnan(absz), np.inf, np.asarray(absz, float))
    dofs = np.asarray(dofs, float)
    finite = np.isfinite(dofs) & (dofs > 0)
    with np.errstate(invalid="ignore"):
        tail = stats.t.sf(absz, np.where(finite, dofs, 1.0))
    return np.where(finite & np.isfinite(absz), stats.norm.isf(tail), absz)


def markdown_table(header: list[str], rows: list[list[Any]]) -> str:
    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def optional_import(name: str) -> Any | None:
    """Import a (sub)module from the `bench` extra, e.g. `scipy.stats.qmc`, or None if missing."""
    try:
        return importlib.import_module(name)
    except ImportError:
        return None


def pyplot(ctx: Any) -> Any | None:
    """`matplotlib.pyplot` on the non-interactive Agg backend, or None (logged) if missing."""
    matplotlib = optional_import("matplotlib")
    if matplotlib is None:
        ctx.log("matplotlib missing: no plot")
        return None
    matplotlib.use("Agg")
    return importlib.import_module("matplotlib.pyplot")
