"""Shared pieces of the benchmark suites: context, results and timing."""

from __future__ import annotations

import dataclasses
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax


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


def block(x: Any) -> Any:
    return jax.block_until_ready(x)


def time_call(fn: Callable[[], Any], *, repeats: int = 5) -> dict[str, float]:
    """Time `fn()`: the first call (compile + run) apart from the steady state.

    Returns `first_s` and `median_s`/`min_s` over `repeats` further calls, each
    ended with `block_until_ready`.
    """
    start = time.perf_counter()
    block(fn())
    first = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        block(fn())
        times.append(time.perf_counter() - start)
    return {"first_s": first, "median_s": statistics.median(times), "min_s": min(times)}


def markdown_table(header: list[str], rows: list[list[Any]]) -> str:
    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def optional_import(name: str) -> Any | None:
    """Import a competitor from the `bench` extra, or None if it is missing."""
    try:
        return __import__(name)
    except ImportError:
        return None
