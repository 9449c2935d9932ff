"""The coverage benchmark's core on two small cells, so the suite cannot rot unnoticed;
and where the main job writes."""

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from benchmarks import coverage, problems
from benchmarks._harness import Context


def test_coverage_core_on_two_cells(tmp_path):
    # A benign integrand and a peak the budget misses, at n = 2^10 with 16 seeds: the
    # first must be covered and not flagged, the second flagged (so it passes the rule).
    benign = coverage.Case(problems.genz_oscillatory(2), "benign", n=2**10)
    missed = coverage.Case(problems.narrow_gaussian(2, 1e-3), "missed peak", n=2**10)
    ctx = Context(quick=False, out=tmp_path)
    result = coverage.measure(ctx, [benign, missed], ["uniform"], seeds=16)

    cells = {r["integrand"]: r for r in result.data["cells"]}
    good, bad = cells[benign.problem.name], cells[missed.problem.name]
    assert good["seeds"] == bad["seeds"] == 16
    # 2-sigma coverage 0.954 over 16 seeds has sd 0.05: 0.65 is about 6 sd below.
    assert good["coverage_2sigma"] >= 0.65
    assert good["flagged"] == 0.0  # no false alarm
    assert 0.5 < good["mean_abs_z"] < 1.3
    # ~0.05 expected hits of the sigma=1e-3 peak per run: the mean is 0 (or one lucky
    # point), the error bar says nothing, the diagnostics must say so.
    assert bad["coverage_2sigma"] < 0.5
    assert bad["flagged"] > 0.5
    assert bad["passes"]
    # (The rule's upper bound, 0.99, means nothing at 16 seeds: `good` may "fail" it.)
    assert ["uniform", missed.problem.name] not in result.data["failing"]
    json.dumps(result.data)  # what the harness writes
    assert missed.problem.name in result.markdown
    for plot in result.plots:
        assert (tmp_path / plot).stat().st_size > 0


def test_coverage_registered_and_not_quick():
    import benchmarks

    assert "coverage" in benchmarks.SUITES and "coverage" in benchmarks.FULL_ONLY
    assert len(coverage.cases()) >= 10
    assert {c.problem.d for c in coverage.cases()} >= {1, 8}
    assert set(coverage.METHODS) == set(coverage._method_builders())


@pytest.mark.parametrize("n, d", [(2**14, 1), (2**14, 3), (2**12, 2), (2**14, 8)])
def test_stratified_grid_fits_the_budget(n, d):
    (c, *_) = counts = coverage._stratified_counts(n, d)
    assert len(counts) == d and 2 * c**d <= n < 2 * (c + 1) ** d


def _git(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True)


def test_main_job_leaves_the_checkout_clean(tmp_path):
    from benchmarks import __main__ as main_job

    root = Path(main_job.__file__).resolve().parents[1]
    if shutil.which("git") is None or _git("rev-parse", cwd=root).returncode != 0:
        pytest.skip("not a git checkout")
    # By default the results go to an ignored folder; the reference results are tracked.
    out = main_job.OUT.resolve() / "summary-quick.md"
    assert _git("check-ignore", "-q", str(out), cwd=root).returncode == 0
    reference = main_job.REFERENCE.resolve() / "summary-quick.md"
    assert _git("ls-files", "--error-unmatch", str(reference), cwd=root).returncode == 0
    # --out still chooses the folder (no suite matches: only the summary is written).
    assert main_job.main(["--quick", "--only", "^$", "--out", str(tmp_path)]) == 0
    assert (tmp_path / "summary-quick.md").read_text().startswith("# jaxmc benchmarks")


def test_quick_settings_name_existing_problems():
    from benchmarks import adaptive, render

    names = {p.name for p in adaptive._problems(quick=True)}
    assert set(adaptive.QUICK_GM) <= names
    assert set(render.QUICK_COMBOS) <= set(render._combos(quick=False))
