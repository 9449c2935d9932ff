"""`python -m benchmarks [--quick] [--only REGEX] [--out DIR]`: run jaxmc's benchmark suites.

Writes `<suite>.json` and `<suite>.md` per suite, the suites' PNG plots, and
`summary.md`: every suite's latest section found in the folder (so `--only`
refreshes some suites without dropping the others'), to `benchmarks/out/`
(untracked, so a run leaves the checkout clean) or `--out`. Quick runs use the
suffix `-quick`. The reference results the documentation shows are committed in
`benchmarks/results/`: `--out benchmarks/results` regenerates them.
"""

from __future__ import annotations

import argparse
import importlib
import json
import platform
import re
import sys
import time
from pathlib import Path

import jax

from . import FULL_ONLY, SUITES
from ._harness import Context, time_call


OUT = Path(__file__).parent / "out"  # ignored by git
REFERENCE = Path(__file__).parent / "results"  # committed: what the documentation shows


def _shown(path: Path) -> str:
    """`path` relative to the working directory when it is under it, as a user would type it."""
    try:
        return str(path.resolve().relative_to(Path.cwd()))
    except ValueError:
        return str(path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__)
    parser.add_argument(
        "--quick", action="store_true", help="small sizes, under 5 minutes on 2 cores"
    )
    parser.add_argument("--only", default=None, help="run only suites whose name matches REGEX")
    parser.add_argument(
        "--out",
        type=Path,
        default=OUT,
        help=f"output folder (default {_shown(OUT)}, untracked; {_shown(REFERENCE)} holds the "
        "committed reference results)",
    )
    args = parser.parse_args(argv)
    start = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    ctx = Context(quick=args.quick, out=args.out)
    environment = {
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "devices": len(jax.devices()),
        "python": platform.python_version(),
        "machine": platform.machine(),
        "quick": args.quick,
    }
    sections = [
        "# jaxmc benchmarks\n",
        f"Setting: {'quick' if args.quick else 'full'}; JAX {environment['jax']} on "
        f"{environment['devices']} {environment['backend']} device(s), Python "
        f"{environment['python']} ({environment['machine']}).\n",
    ]
    failures = 0
    suffix = "-quick" if args.quick else ""
    for name in SUITES:
        if args.only and not re.search(args.only, name):
            continue
        if args.quick and name in FULL_ONLY:
            print(f"[{name}] has no quick setting, skipped", file=sys.stderr)
            continue
        try:
            module = importlib.import_module(f".{name}", __package__)
        except ModuleNotFoundError as error:
            if error.name == f"{__package__}.{name}":
                print(f"[{name}] not available in this checkout, skipped", file=sys.stderr)
                continue
            raise
        title = getattr(module, "TITLE", name)
        print(f"[{name}] {title}", file=sys.stderr, flush=True)
        # CPU seconds (all threads) beside the wall time: on a shared machine the wall
        # time grows with the load, the CPU time much less.
        cpu_start = time.process_time()
        try:
            timing = time_call(lambda: module.run(ctx), repeats=0)
        except Exception as error:  # one broken suite should not hide the others' results
            failures += 1
            print(f"[{name}] FAILED: {error!r}", file=sys.stderr, flush=True)
            section = args.out / f"{name}{suffix}.md"
            section.write_text(f"## {title}\n\nFAILED: `{error!r}`\n")
            continue
        result, elapsed = timing.output, timing.first_s
        cpu = time.process_time() - cpu_start
        print(f"[{name}] done in {elapsed:.1f} s ({cpu:.1f} s CPU)", file=sys.stderr, flush=True)
        payload = {
            "suite": name,
            "environment": environment,
            "seconds": elapsed,
            "cpu_seconds": cpu,
            **result.data,
        }
        (args.out / f"{name}{suffix}.json").write_text(json.dumps(payload, indent=2, default=float))
        plots = "".join(f"\n![{p}]({p})\n" for p in result.plots)
        section = f"## {title}\n\n{result.markdown}\n{plots}\n_{elapsed:.1f} s ({cpu:.1f} s CPU)_\n"
        (args.out / f"{name}{suffix}.md").write_text(section)
    for name in SUITES:
        section = args.out / f"{name}{suffix}.md"
        if section.exists():
            sections.append(section.read_text())
    summary = args.out / f"summary{suffix}.md"
    summary.write_text("\n".join(sections))
    print(
        f"done in {time.perf_counter() - start:.0f} s ({time.process_time():.0f} s CPU); "
        f"results in {_shown(args.out)}/, summary {_shown(summary)}",
        file=sys.stderr,
    )
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
