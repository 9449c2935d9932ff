"""`python -m benchmarks [--quick] [--only REGEX] [--out DIR]`: run jaxmc's benchmark suites.

Writes `<suite>.json` and `<suite>.md` per suite, the suites' PNG plots, and
`summary.md`: every suite's latest section found in the folder (so `--only`
refreshes some suites without dropping the others'), to `benchmarks/results/`
(or `--out`). Quick runs use the suffix `-quick`.
"""

from __future__ import annotations

import argparse
import importlib
import json
import platform
import re
import sys
from pathlib import Path

import jax

from . import FULL_ONLY, SUITES
from ._harness import Context, time_call


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__)
    parser.add_argument("--quick", action="store_true", help="small sizes, a few minutes in all")
    parser.add_argument("--only", default=None, help="run only suites whose name matches REGEX")
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).parent / "results", help="output folder"
    )
    args = parser.parse_args(argv)
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
        try:
            timing = time_call(lambda: module.run(ctx), repeats=0)
        except Exception as error:  # one broken suite should not hide the others' results
            failures += 1
            print(f"[{name}] FAILED: {error!r}", file=sys.stderr, flush=True)
            section = args.out / f"{name}{suffix}.md"
            section.write_text(f"## {title}\n\nFAILED: `{error!r}`\n")
            continue
        result, elapsed = timing.output, timing.first_s
        print(f"[{name}] done in {elapsed:.1f} s", file=sys.stderr, flush=True)
        payload = {"suite": name, "environment": environment, "seconds": elapsed, **result.data}
        (args.out / f"{name}{suffix}.json").write_text(json.dumps(payload, indent=2, default=float))
        plots = "".join(f"\n![{p}]({p})\n" for p in result.plots)
        section = f"## {title}\n\n{result.markdown}\n{plots}\n_{elapsed:.1f} s_\n"
        (args.out / f"{name}{suffix}.md").write_text(section)
    for name in SUITES:
        section = args.out / f"{name}{suffix}.md"
        if section.exists():
            sections.append(section.read_text())
    summary = args.out / f"summary{suffix}.md"
    summary.write_text("\n".join(sections))
    print(f"wrote {summary}", file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
