"""The garment size study's own reading: the PETSc stages of a run's
-log_view file, a case's record from a run of its own, and a case it does
not know refused in one line."""

import json
import os
import subprocess
import sys

import pytest
from mpi4py import MPI

pytestmark = pytest.mark.skipif(MPI.COMM_WORLD.size > 1,
                                reason="runs knitfem in subprocesses")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def study(*args, cwd):
    env = dict(os.environ, PYTHONPATH=ROOT)
    return subprocess.run([sys.executable, "-m", "benchmarks.garment_size", *args,
                           "-bench_results", str(cwd / "results"), "-skip_petscrc"],
                          capture_output=True, text=True, env=env, cwd=cwd, timeout=300)


def test_a_case_is_recorded_from_its_own_process(tmp_path):
    """The smallest reduced sleeve for one step: its stages add up to no more
    than the process, its Newton iterations are the summary's, and its
    volume control points are a third of its unknowns; a full run of the
    same size recorded before, not run now, is kept and not compared."""
    os.symlink(os.path.join(ROOT, "benchmarks"), tmp_path / "benchmarks")
    os.mkdir(tmp_path / "results")          # a full run recorded before, its output gone
    with open(os.path.join(ROOT, "benchmarks", "results", "garment_size.json")) as f:
        full = dict(json.load(f)["cases"]["sleeve_16x10_full"], window_s=0.01, process_s=1.0)
    with open(tmp_path / "results" / "garment_size.json", "w") as f:
        json.dump({"study": "garment_size", "cases": {"sleeve_16x10_full": full}}, f)
    p = study("-bench_cases", "sleeve_16x10_reduced", "-bench_window", "0.01", cwd=tmp_path)
    assert p.returncode == 0, p.stdout + p.stderr
    rec = json.load(open(tmp_path / "results" / "garment_size.json"))
    case = rec["cases"]["sleeve_16x10_reduced"]
    summary = json.load(open(tmp_path / "out" / "benchmarks" / "garment_size"
                             / "sleeve_16x10_reduced" / "summary.json"))
    stages = case["stages_s"]
    assert set(stages) == {"Model set-up", "Solver set-up", "Time stepping"}
    assert 0 < sum(stages.values()) < case["process_s"]
    assert case["newton"] == summary["newton_iterations"] > 0 and case["steps"] == 1
    assert case["volume_control_points"] * 3 == case["unknowns"] == 216
    assert case["yarn_control_points"] == summary["yarn_control_points"] == 1280
    assert case["newton_s"] == stages["Time stepping"] / case["newton"]
    assert case["memory"]["peak_rss_mib_max"] > 50
    assert "against_full" not in case and rec["cases"]["sleeve_16x10_full"]["process_s"] == 1.0


def test_an_unknown_case_is_one_line(tmp_path):
    os.symlink(os.path.join(ROOT, "benchmarks"), tmp_path / "benchmarks")
    p = study("-bench_cases", "sleeve_7x7_reduced", cwd=tmp_path)
    assert p.returncode == 2
    lines = p.stdout.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        "benchmarks.garment_size: error: -bench_cases sleeve_7x7_reduced: use some of "
        "sleeve_16x10_full,sleeve_16x10_reduced,")
