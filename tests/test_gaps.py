"""The smallest yarn gap (``knitfem.contact.gaps``): against every pair of
points, and the same number as the summary of a run and the acceptance
checks' reader of its XDMF series."""

import importlib.util
import json
import os
import subprocess
import sys

import numpy as np
import pytest
from mpi4py import MPI

from knitfem import io
from knitfem.contact.gaps import YarnGaps
from knitfem.knit.pattern import Jersey, jersey_fabric

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# an independent reader of the same measure, where the steering files lie beside
# the project (or
# beside a worktree's parent)
CHECKER = next((c for c in (os.path.join(up, "shared", "checks", "lib", "yarn_gaps.py")
                            for up in (os.path.dirname(ROOT),
                                       os.path.dirname(os.path.dirname(ROOT))))
                if os.path.exists(c)), "")


def every_pair(pts, radius):
    """D by all pairs: arclength along each yarn's chords, the short way round
    a yarn whose ends meet, capped at 1."""
    nyarn, m = pts.shape[:2]
    s = np.concatenate([np.zeros((nyarn, 1)), np.cumsum(
        np.linalg.norm(np.diff(pts, axis=1), axis=-1), axis=1)], axis=1)
    ends = np.linalg.norm(pts[:, 0] - pts[:, -1], axis=-1)
    loop = np.where(ends < 1e-3 * s[:, -1], s[:, -1], np.inf)
    P, s = pts.reshape(-1, 3), s.ravel()
    yarn, loop = np.repeat(np.arange(nyarn), m), np.repeat(loop, m)
    d = np.linalg.norm(P[:, None] - P[None], axis=-1)
    along = np.abs(s[:, None] - s[None])
    along = np.minimum(along, loop[:, None] - along)
    counted = (yarn[:, None] != yarn[None]) | (along > 8 * radius)
    return min(1.0, d[counted].min() / (2 * radius))


@pytest.mark.parametrize("knit,amount", [("flat", 0.0), ("flat", 4e-4),
                                         ("tube", 4e-4)])
def test_gap_equals_the_smallest_over_every_pair(knit, amount):
    """Rest and shaken knits (control points moved by up to ~r): the k-d tree
    misses no pair, and a closed yarn is measured the short way round."""
    fab = jersey_fabric(Jersey(3, 3, knit=knit))
    rng = np.random.default_rng(1)
    P = fab.curves(fab.X + amount * rng.normal(size=fab.X.shape))
    rest = io.centrelines(fab.curves(fab.X))
    pts = io.centrelines(P)
    gaps = YarnGaps(rest, fab.radius)
    by_yarn = [S.points.reshape(S.nyarn, -1, 3) for S in (rest, pts)]  # one length
    expected = tuple(every_pair(S, fab.radius) for S in by_yarn)
    assert (gaps.frame(rest), gaps.add(0.5, pts)) == expected
    assert expected[1] < 1.0 or not amount      # shaken, pieces overlap
    assert gaps.record() == dict(min_yarn_gap=expected[1], min_yarn_gap_time_s=0.5)


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="runs knitfem in a subprocess")
@pytest.mark.skipif(not CHECKER, reason="no acceptance checks here")
def test_summary_gap_is_the_checkers_on_the_series(tmp_path, capsys):
    """A short run's summary.json reports the smallest gap over its output
    frames, equal to what ``checks/lib/yarn_gaps.py`` reads from its XDMF."""
    env = dict(os.environ, PYTHONPATH=ROOT)
    p = subprocess.run([sys.executable, "-m", "knitfem.cli", "run", "-knit_rows", "3",
                        "-knit_cols", "3", "-knit_t_end", "0.02", "-knit_snapshots",
                        "", "-o", str(tmp_path), "-skip_petscrc"],
                       capture_output=True, text=True, env=env, timeout=300)
    assert p.returncode == 0, p.stdout + p.stderr
    rec = json.loads((tmp_path / "summary.json").read_text())
    spec = importlib.util.spec_from_file_location("yarn_gaps", CHECKER)
    checker = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(checker)
    capsys.readouterr()
    checker.main(str(tmp_path / "yarns.xdmf"))
    _, t, gap = capsys.readouterr().out.split()
    assert float(t) == rec["min_yarn_gap_time_s"]
    assert f"{rec['min_yarn_gap']:.4f}" == gap
