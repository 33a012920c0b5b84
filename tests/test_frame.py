"""A knit that does not care which way it faces: a free jersey started
rigidly turned is strained by nothing in every model, about every axis, with
and without gravity; the holds; the corner-hung drape, static and dynamic."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from petsc4py import PETSc

from helpers import COMM, jersey, mixed, models, region
from knitfem.model.full import Material
from knitfem.knit.pattern import HOLDS, Jersey, jersey_fabric
from knitfem.cli.scenes import make_fabric, rotation
from solvers.integrators import BackwardEuler

TURNS = [(45, 0, 0), (0, 45, 0), (0, 0, 45)]


def system_of(kind, fabric, gravity):
    full, red = models(COMM, fabric, Material(gravity=gravity))
    if kind == "full":
        return full
    if kind == "reduced":
        return red
    if kind == "sampled":           # any sampled set and weights will do
        from knitfem.lod.reduced import ReducedModel
        from knitfem.lod.sampling import SampledElements

        rng = np.random.default_rng(COMM.rank)
        some = rng.choice(full.elements.ne, full.elements.ne // 4, replace=False)
        return ReducedModel(full, red.embedding, SampledElements(
            full, red.embedding, some, rng.uniform(0.5, 5.0, len(some))))
    return mixed(full, red, region(full, red, [(4, 5, 4, 6)]))


@pytest.mark.parametrize("gravity", [0.0, 9.81])
@pytest.mark.parametrize("turn", TURNS)
@pytest.mark.parametrize("kind", ["full", "reduced", "sampled", "mixed"])
def test_started_turned_strains_nothing(kind, turn, gravity):
    """Started turned, a free 6 x 6 jersey keeps E_el and |g| at round-off
    over five implicit steps: at rest without gravity, falling rigidly with."""
    fabric = jersey(6, 6).started_turned(rotation(turn))
    system = system_of(kind, fabric, gravity)
    x = system.start_state()
    eps = system.full_state(x)
    lo, hi = eps.getOwnershipRange()
    turned = fabric.start_points().ravel()[lo:hi]
    assert np.abs(eps.getArray() - turned).max() < 1.5e-16  # measured 1.4e-17 (2.1e-17 before)
    # the start is the rest turned, not the rest: contacts hold there
    assert np.abs(turned - fabric.X.ravel()[lo:hi]).max() > fabric.radius
    v = x.duplicate()
    v.zeroEntries()
    integ = BackwardEuler(system, 1e-3)
    g = system.C.createVecLeft()
    for n in range(5):
        integ.step(n * 1e-3, x, v)
    system.constraint_residual(x, g)
    assert system.elastic_energy(x) < 8e-28  # measured 7.1e-29
    assert g.getSize() == 0 or g.norm(PETSc.NormType.INFINITY) < 1e-12 * fabric.radius
    # a rigid fall, backward Euler's: y_n = −g h² n(n + 1)/2
    moved = (system.full_state(x).getArray() - turned).reshape(-1, 3)
    drop = -gravity * 1e-6 * 15
    assert np.allclose(moved, [0, drop, 0], rtol=0, atol=1e-14 + 1e-9 * abs(drop))


def test_rotation_turns_about_x_then_y_then_z():
    Rx, Ry, Rz = (rotation(t) for t in ((90, 0, 0), (0, 90, 0), (0, 0, 90)))
    assert np.allclose(Rx @ [0, 1, 0], [0, 0, 1], atol=1e-15)
    assert np.allclose(Ry @ [0, 0, 1], [1, 0, 0], atol=1e-15)
    assert np.allclose(Rz @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    # measured 0
    assert np.allclose(rotation((90, 90, 90)), Rz @ Ry @ Rx, atol=0, rtol=5e-15)
    # measured 2.2e-16
    R = rotation((30, -60, 120))
    assert np.allclose(R @ R.T, np.eye(3), atol=3e-15, rtol=0)


def test_holds():
    """top: the heads of the top course; side: the first stitch of every
    course; corner: the top course's first stitch."""
    j = Jersey(3, 4)
    heads = j.heads(2)
    top, side, corner = (jersey_fabric(j, hold=h).fixed for h in HOLDS)
    assert np.array_equal(top[0], [2] * 4) and np.array_equal(top[1], heads)
    assert np.array_equal(side[0], [0, 1, 2]) and np.all(side[1] == heads[0])
    assert np.array_equal(corner[0], [2]) and np.array_equal(corner[1], heads[:1])
    with pytest.raises(ValueError, match="use one of top, side, corner"):
        jersey_fabric(j, hold="bottom")
    # the scene keeps the holds of the rest where a turned start puts them
    fab = make_fabric("hanging", j, hold="corner", tilt=0.0, start_rotation=(0, 0, 30))
    # measured 0
    assert np.allclose(fab.start_points(), fab.turn(fab.X), atol=0, rtol=5e-15)


def knitfem_run(out, *args):
    env = dict(os.environ, PYTHONPATH=os.path.dirname(os.path.dirname(__file__)))
    p = subprocess.run([sys.executable, "-m", "knitfem.cli", "run", "-knit_hold",
                        "corner", "-knit_rows", "4", "-knit_cols", "4", "-o", str(out),
                        *args, "-skip_petscrc"], capture_output=True, text=True,
                       env=env, timeout=300)
    assert p.returncode == 0, p.stdout + p.stderr
    return json.loads((out / "summary.json").read_text())


@pytest.mark.skipif(COMM.size > 1, reason="runs knitfem in subprocesses")
def test_corner_hung_static_and_dynamics_agree(tmp_path):
    """Heavily damped, the dynamics is a gradient flow of the energy and comes
    to rest where the static solver (a pseudo-time gradient flow) goes: the
    same centroid and energies. (Lightly damped, a swing can carry the knit
    into another of its equilibria.) The centroid hangs below the corner."""
    static = knitfem_run(tmp_path / "static", "-knit_static")
    dyn = knitfem_run(tmp_path / "dynamic", "-knit_damping", "20", "-knit_t_end", "2")
    hold_y = 0.0147                                   # the corner's height
    drop = hold_y - static["centroid"][1]
    assert drop > 0.01
    assert dyn["kinetic_energy"] < 6e-12 * dyn["total_energy"]  # measured 5e-13
    # measured 4.0e-7 of the drop
    assert np.allclose(dyn["centroid"], static["centroid"], rtol=0, atol=3e-6 * drop)
    assert abs(static["centroid"][0]) < 1e-12 * drop  # below the corner: 1.5e-13 measured
    # measured 1.5e-12 and 3.1e-7 (the total is stationary at the minimum)
    for name, rel in (("total_energy", 1e-11), ("elastic_energy", 2e-6)):
        assert dyn[name] == pytest.approx(static[name], rel=rel, abs=0)
    assert static["max_contact_residual"] < 2e-17  # measured 1.7e-18


@pytest.mark.skipif(COMM.size > 1, reason="runs knitfem in subprocesses")
def test_scene_guide_frame_commands_run_as_written(tmp_path):
    """The scene guide's corner-hung drape and turned start, as written (in
    a scratch directory): the drape hangs below its corner, the turned start
    rests unstrained."""
    from benchmarks.doc_commands import doc_commands

    env = dict(os.environ, PATH=os.path.dirname(sys.executable) + os.pathsep
               + os.environ["PATH"])
    lines = [ln for doc, ln in doc_commands() if doc == "docs/guide/scenes.md"
             and ("-knit_hold corner" in ln or "-knit_start_rotation" in ln)]
    assert len(lines) == 2
    for line in lines:
        p = subprocess.run(line.split() + ["-skip_petscrc"], capture_output=True,
                           text=True, env=env, cwd=tmp_path, timeout=300)
        assert p.returncode == 0, (line, p.stdout + p.stderr)
    corner = json.loads((tmp_path / "out/corner/summary.json").read_text())
    turned = json.loads((tmp_path / "out/turned/summary.json").read_text())
    assert abs(corner["centroid"][0]) < 1e-6 and corner["max_contact_residual"] < 1e-15
    assert turned["elastic_energy"] < 1e-20 and turned["kinetic_energy"] < 1e-20
    assert turned["max_constraint_violation"] < 9e-17  # measured 8.4e-18
