"""A naturally straight yarn relaxed into its loops (``knitfem relax``), and
scenes started from the relaxed knit (``-knit_rest``)."""

import json
import os
import subprocess
import sys

import meshio
import numpy as np
import pytest
from mpi4py import MPI

from petsc4py import PETSc

from knitfem.knit.pattern import Jersey, jersey_fabric
from knitfem.model.full import FullModel, Material
from knitfem.run.relax import (Ramp, RelaxedKnit, natural_fabric, shortest_loop,
                               stitch_length, stress_free, yarn_lengths)
from knitfem.yarn.elements import YarnElements

pytestmark = pytest.mark.skipif(MPI.COMM_WORLD.size > 1,
                                reason="runs knitfem in subprocesses")


def knitfem(*args):
    env = dict(os.environ, PYTHONPATH=os.path.dirname(os.path.dirname(__file__)))
    return subprocess.run([sys.executable, "-m", "knitfem.cli", *args, "-skip_petscrc"],
                          capture_output=True, text=True, env=env, timeout=600)


def test_natural_fabric_has_the_loop_length_asked_and_no_natural_curvature():
    j = Jersey(3, 4)
    template = jersey_fabric(j)
    fab = natural_fabric(j, template, 20e-3, scale=(1.2, 1.0, 1.0))
    ell = yarn_lengths(fab) / j.cols
    # measured 3.3e-16 and 0
    assert ell == pytest.approx(np.full(3, 20e-3 * ell[0] / ell.mean()), rel=2e-15, abs=0)
    assert ell.mean() == pytest.approx(20e-3, rel=2e-15, abs=0)
    el = YarnElements(fab.X, fab.connectivity(0, fab.nyarn), 1, 1, 1,
                      natural=fab.natural)
    assert not el.kappa0.any() and fab.separation == 2 * j.radius
    # the start is the rest X (the template at 20 mm a stitch) stretched along
    # the courses about its centroid
    c = fab.X.mean(axis=0)
    assert np.allclose(fab.start_X - c, (fab.X - c) * [1.2, 1.0, 1.0],
                       rtol=0, atol=1e-17)  # measured 1.7e-18 (points to 19 mm)
    assert fab.contact_X is template.X    # the yarn contact's rest gaps
    back = stress_free(fab)
    assert back.X is fab.start_X and not back.natural and back.separation is None


def test_relaxed_knit_file_round_trip_and_mismatch(tmp_path):
    j = Jersey(2, 3)
    fab = natural_fabric(j, jersey_fabric(j))
    knit = RelaxedKnit(2, 3, "flat", j.radius, fab.X, fab.X + 1e-4, fab.contacts,
                       fab.separation, 0.0168, yarn_contact=False)
    knit.save(str(tmp_path / "relaxed.h5"))
    back = RelaxedKnit.load(str(tmp_path / "relaxed.h5"))
    assert np.array_equal(back.positions, knit.positions) and not back.yarn_contact
    assert all(np.array_equal(a, b) for a, b in zip(back.contacts, knit.contacts))
    with pytest.raises(ValueError, match="give the same -knit_rows"):
        back.check(Jersey(3, 3))


@pytest.mark.parametrize("contacts", ["fixed", "sliding"])
def test_the_ramp_starts_consistent_and_ends_at_the_natural_knit(contacts):
    """At λ = 0 the start, stretched 20 % along the wales and of a loop
    length 5 % short, is stretch-free, and the natural rest X (the template
    at the loop length) keeps its crossings (g = 0 to round-off: measured 0
    fixed, 1e-19 m sliding), which the stretched start does not; at λ = 1 the rest
    quantities are exactly the natural knit's (its line elements, held
    separations and invariants: (1 − λ) start + λ end is end)."""
    j = Jersey(3, 3)
    template = jersey_fabric(j)
    fab = natural_fabric(j, template, 0.95 * 16.82e-3, scale=(1.0, 1.2, 1.0))
    system = FullModel(PETSc.COMM_WORLD, fab, Material(gravity=0.0),
                       contacts=contacts)
    el, x0 = system.elements, system.start_state()
    held = system.constraints.local
    kept = (lambda: held.rest) if contacts == "fixed" else (lambda: held.delta)
    natural = el.W.copy(), el.Xp2.copy(), kept().copy()
    ramp = Ramp(system, x0)
    ramp.set(0.0)
    g = system.C.createVecLeft()
    system.constraint_residual(system.rest_state(), g)
    assert g.norm(PETSc.NormType.INFINITY) < 1e-18
    system.constraint_residual(x0, g)
    assert g.norm(PETSc.NormType.INFINITY) > 1e-6
    assert np.abs(el.strain(system.yarn_points(x0))).max() < 1.5e-15  # measured 2.0e-16
    ramp.set(1.0)
    assert np.array_equal(el.W, natural[0]) and np.array_equal(el.Xp2, natural[1])
    assert np.array_equal(kept(), natural[2])
    touching = held.rest[:, 0] ** 0.5 if contacts == "fixed" else held.delta
    assert np.allclose(touching, 2 * j.radius, rtol=1e-15, atol=0)  # measured 0


def relaxed(tmp_path, name, *args, contact="off"):
    out = tmp_path / name
    p = knitfem("relax", "-knit_rows", "3", "-knit_cols", "3", "-knit_yarn_contact",
                contact, *args, "-o", str(out))
    assert p.returncode == 0, p.stderr
    return out, json.loads((out / "summary.json").read_text())


def test_relax_then_a_free_run_stays_put(tmp_path):
    """The relaxed knit is at rest (residual acceleration below
    -knit_rest_accel), and a free run without gravity from it moves no point
    more than 4e-9 r full (its prestress balanced by the crossings) and
    6e-12 r reduced (its rest the relaxed knit): measured 6.2e-10 r and
    8.3e-13 r."""
    out, rec = relaxed(tmp_path, "relax")
    assert rec["status"] == "completed" and rec["residual_acceleration_m_s2"] < 1e-4
    assert rec["chart"] == ["KKK"] * 3 and rec["steps"] == 5
    assert rec["loop_length_m"] == pytest.approx(16.82e-3, rel=5e-5)  # measured 6.8e-6
    for key in ("course_spacing_m", "wale_spacing_m", "k_c", "k_w", "k_s"):
        assert rec[key] > 0
    assert rec["k_s"] == rec["k_c"] * rec["k_w"]          # exactly: its definition
    series = meshio.xdmf.TimeSeriesReader(str(out / "relaxed.xdmf"))
    series.read_points_cells()
    assert series.num_steps == 6 and (out / "relaxed.png").exists()
    for model in ("full", "reduced"):
        run = tmp_path / model
        p = knitfem("run", "-knit_scene", "freefall", "-knit_gravity", "0",
                    "-knit_rows", "3", "-knit_cols", "3", "-knit_rest",
                    str(out / "relaxed.h5"), "-knit_model", model, "-knit_t_end",
                    "0.05", "-o", str(run))
        assert p.returncode == 0, p.stderr
        r = meshio.xdmf.TimeSeriesReader(str(run / "yarns.xdmf"))
        r.read_points_cells()
        P = [r.read_data(k)[1]["position"] for k in range(r.num_steps)]
        bound = {"full": 4e-9, "reduced": 6e-12}[model]
        assert np.abs(P[-1] - P[0]).max() < bound * 5e-4, model


@pytest.mark.parametrize("contact", ["on", "off"])
def test_the_relaxed_knit_forgets_its_template(tmp_path, contact):
    """Started 20 % stretched along the wales it relaxes to the very knit it
    relaxes to from the template, every control point the same to the last
    bit: after the first load step, whose minimum is unique, the state is
    rounded and the solver and the yarn contact start afresh, so the rest of
    the path depends on that state alone. Before, the two ended 5e-10 apart
    in k_w with the yarn contact, and without it round-off picked one of two
    minima (k_c 4.49 or 4.60)."""
    out_a, a = relaxed(tmp_path, "a", contact=contact)
    out_b, b = relaxed(tmp_path, "b", "-knit_template_scale", "1,1.2,1", contact=contact)
    for k in ("k_c", "k_w"):
        assert b[k] == a[k], k
    knits = [RelaxedKnit.load(str(o / "relaxed.h5")) for o in (out_a, out_b)]
    assert np.array_equal(knits[0].positions, knits[1].positions)


def test_rest_of_other_stitches_is_refused(tmp_path):
    j = Jersey(2, 3)
    fab = natural_fabric(j, jersey_fabric(j))
    RelaxedKnit(2, 3, "flat", j.radius, fab.X, fab.X, fab.contacts, fab.separation,
                0.0168).save(str(tmp_path / "relaxed.h5"))
    p = knitfem("run", "-knit_rows", "4", "-knit_rest", str(tmp_path / "relaxed.h5"),
                "-o", str(tmp_path / "out"))
    assert p.returncode == 2
    assert p.stderr.strip().count("\n") == 0 and "give the same" in p.stderr


def test_relax_options_take_effect(tmp_path):
    """-knit_loop_length sets the yarn a stitch (6 % shorter than the
    template's; the relaxed knit's within its strain), -knit_template_scale
    the start (the series' first frame is the template at that loop length
    stretched 1.01 along the courses), -knit_load_steps the steps, -knit_rest_accel when it stops
    (its residual below it, in fewer iterations than to the default)."""
    _, plain = relaxed(tmp_path, "plain", "-knit_loop_length", "0.0158")
    out, rec = relaxed(tmp_path, "relax", "-knit_loop_length", "0.0158",
                       "-knit_template_scale", "1.01,1,1", "-knit_rest_accel",
                       "1", "-knit_load_steps", "2")
    assert rec["loop_length_m"] == pytest.approx(0.0158, rel=5e-5)  # measured 6.9e-6
    assert rec["template_scale"] == [1.01, 1.0, 1.0] and rec["steps"] == 2
    assert rec["residual_acceleration_m_s2"] < 1
    assert plain["residual_acceleration_m_s2"] < 1e-4
    assert rec["newton_iterations"] < plain["newton_iterations"]
    series = meshio.xdmf.TimeSeriesReader(str(out / "relaxed.xdmf"))
    series.read_points_cells()
    first = series.read_data(0)[1]["position"]
    fab = jersey_fabric(Jersey(3, 3))
    width = np.ptp(fab.curves(fab.X).samples(8).points[:, 0])
    ell0 = stitch_length(Jersey(3, 3), fab)
    # the start: the template at 0.0158 stretched along the courses
    # (measured 2.2e-16)
    assert np.ptp(first[:, 0]) == pytest.approx(1.01 * width * 0.0158 / ell0,
                                                rel=1e-14, abs=0)


def test_a_loop_too_short_for_the_yarn_is_refused(tmp_path):
    """With the yarn contact on, a loop length under which the template's
    yarns come within 2r (ℓ₀ / 1.0431: the crossings') is a one-line error
    that gives the shortest, and that loop length relaxes."""
    j = Jersey(3, 3)
    template = jersey_fabric(j)
    least = shortest_loop(j, template)
    # the crossings' 1.0431 × 2r, sampled 8 times a segment: measured 2.9e-4
    assert least == pytest.approx(stitch_length(j, template) / 1.0431, rel=1e-3)
    p = knitfem("relax", "-knit_rows", "3", "-knit_cols", "3", "-knit_loop_length",
                "0.0158", "-o", str(tmp_path / "short"))
    assert p.returncode == 2 and p.stderr.strip().count("\n") == 0
    said = p.stderr.split("give at least ")[1].split()[0]
    assert float(said) >= least and "-knit_yarn_contact off" in p.stderr
    _, rec = relaxed(tmp_path, "least", "-knit_loop_length", said, contact="on")
    assert rec["min_yarn_gap"] >= 0.95


def test_an_interrupted_relaxation_continues_as_it_says(tmp_path):
    """SIGINT: exit 130, one line with the command that continues, the summary
    marked interrupted and no relaxed.h5 (an earlier one is removed at the
    start); that command, run as printed, finishes the relaxation."""
    import shlex
    import signal
    import time

    out = tmp_path / "relax"
    out.mkdir()
    (out / "relaxed.h5").write_text("an earlier relaxation's")
    env = dict(os.environ, PYTHONPATH=os.path.dirname(os.path.dirname(__file__)))
    args = ["relax", "-knit_rows", "4", "-knit_cols", "4", "-knit_load_steps", "10",
            "-o", str(out)]
    p = subprocess.Popen([sys.executable, "-m", "knitfem.cli", *args, "-skip_petscrc"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env=env)
    t0 = time.time()
    while not (out / "relaxed" / "00000002.h5").exists() and time.time() - t0 < 120:
        time.sleep(0.05)
    p.send_signal(signal.SIGINT)
    stdout, stderr = p.communicate(timeout=120)
    assert p.returncode == 130, stdout + stderr
    said = [s for s in stdout.splitlines() if "continue with: " in s]
    assert len(said) == 1 and not (out / "relaxed.h5").exists()
    assert json.loads((out / "summary.json").read_text())["status"] == \
        "interrupted by SIGINT"
    again = shlex.split(said[0].split("continue with: ")[1])
    assert again[0] == "knitfem"
    p = subprocess.run([sys.executable, "-m", "knitfem.cli", *again[1:], "-skip_petscrc"],
                       capture_output=True, text=True, env=env, timeout=300)
    assert p.returncode == 0, p.stderr
    assert RelaxedKnit.load(str(out / "relaxed.h5")).rows == 4
