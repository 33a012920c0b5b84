"""The command line: tables from assembled objects, one-line errors."""

import json
import os
import re
import subprocess
import sys

import pytest
from mpi4py import MPI

pytestmark = pytest.mark.skipif(MPI.COMM_WORLD.size > 1,
                                reason="runs knitfem in subprocesses")


def knitfem(*args, cwd=None):
    env = dict(os.environ, PYTHONPATH=os.path.dirname(os.path.dirname(__file__)))
    return subprocess.run([sys.executable, "-m", "knitfem.cli", *args, "-skip_petscrc"],
                          capture_output=True, text=True, env=env, cwd=cwd, timeout=300)


def test_dofs_table_paper_case():
    p = knitfem("dofs", "-knit_rows", "15", "-knit_cols", "30", "-knit_lod", "5,5",
                "-knit_format", "json")
    assert p.returncode == 0, p.stderr
    rec = json.loads(p.stdout)
    assert rec["control_points_per_yarn"] == 243
    assert rec["dofs"] == 10935
    assert rec["reduced_dofs"] == 150
    assert rec["reduced_control_points"] == 50
    assert rec["scalar_constraints"] == 3 * 2 * 30 * 14
    assert rec["unknowns"] == 10935 + 2520
    assert rec["ratio"] == pytest.approx(13455 / 150)


def test_dofs_table_text():
    p = knitfem("dofs", "-knit_rows", "2", "-knit_cols", "3")
    assert p.returncode == 0, p.stderr
    assert "Scalar unknowns total" in p.stdout


@pytest.mark.parametrize("args,word", [
    (["-knit_rows", "0"], "-knit_rows"),
    (["-knit_cols", "abc"], "-knit_cols"),
    (["-knit_radius", "-1"], "-knit_radius"),
    (["-knit_format", "xml"], "-knit_format"),
    (["-knit_lod", "5"], "-knit_lod"),
])
def test_bad_input_one_line_exit_2(args, word):
    p = knitfem("dofs", *args)
    assert p.returncode == 2
    out = (p.stdout + p.stderr).strip().splitlines()
    assert len(out) == 1 and word in out[0] and "Traceback" not in p.stderr


def test_unknown_command():
    p = knitfem("fly")
    assert p.returncode == 2 and len(p.stdout.strip().splitlines()) == 1


def test_pattern_writes_geometry_and_picture(tmp_path):
    p = knitfem("pattern", "-knit_rows", "3", "-knit_cols", "3", "-o", str(tmp_path))
    assert p.returncode == 0, p.stderr
    import meshio
    mesh = meshio.read(tmp_path / "jersey_3x3.vtu")
    assert "radius" in mesh.point_data and len(mesh.cells_dict["line"]) > 0
    assert (tmp_path / "jersey_3x3.png").stat().st_size > 10000


def test_deform_metrics(tmp_path):
    def metrics(amount):
        p = knitfem("deform", "-knit_mode", "traction", "-knit_amount", amount,
                    "-knit_rows", "3", "-knit_cols", "3", "-o", str(tmp_path))
        assert p.returncode == 0, p.stderr
        return json.loads((tmp_path / "metrics.json").read_text())

    rest = metrics("1.0")               # identity: the fitting is exact
    assert rest["max_strain"] < 1e-12 and rest["max_contact_residual_over_r"] < 1e-10
    assert not rest["penetration"]
    pulled = metrics("1.2")             # 20 % along the courses
    assert 0.1 < pulled["max_strain"] < 0.25
    assert (tmp_path / "traction.png").exists()


def test_run_writes_output_and_log_view_has_a_stage_per_phase(tmp_path):
    p = knitfem("run", "-knit_scene", "hanging", "-knit_rows", "2", "-knit_cols", "2",
                "-knit_t_end", "0.04", "-knit_dt", "1e-2", "-knit_snapshots", "0.02,0.04", "-o",
                str(tmp_path), "-log_view")
    assert p.returncode == 0, p.stderr
    stages = re.findall(r"^\s*\d+:\s+([^:]+):", p.stdout, flags=re.M)
    assert {"Model set-up", "Solver set-up", "Time stepping"} <= set(stages)
    rec = json.loads((tmp_path / "summary.json").read_text())
    for key in ("scene", "model", "steps", "t_end", "wall_time_s", "unknowns",
                "centroid", "lowest_point", "kinetic_energy", "elastic_energy",
                "max_constraint_violation", "max_strain"):
        assert key in rec
    assert rec["steps"] == 4 and rec["sag"] > 0     # the tilted swatch falls
    for name in ("hanging_t0.02s.png", "hanging_t0.04s.png", "hanging_snapshots.png",
                 "yarns.xdmf", "yarns.h5"):
        assert (tmp_path / name).stat().st_size > 0
