"""Yarns of their own lengths: a shaped jersey (courses of different stitch
counts) and a carrier's yarn that knits two courses. They assemble, keep
their mass, move in every model as one rank's, care not which way they
face, and their output knows each point's course."""

import meshio
import numpy as np
import pytest
from petsc4py import PETSc

from helpers import (COMM, gather, mixed, models, region, run, shaped,
                     steps_from_start, two_courses_one_yarn)
from knitfem.cli.scenes import rotation
from knitfem.model.assembly import YarnLayout
from knitfem.model.full import Material
from knitfem.yarn import bspline
from solvers.integrators import BackwardEuler

SELF = PETSc.COMM_SELF
STITCHES = (6, 5, 5, 3, 4)
FABRICS = {"shaped": lambda hold=None: shaped(STITCHES, hold),
           "joined": lambda hold=None: two_courses_one_yarn(4, hold)}


def rest_length(fab, nq=12):
    """Σ_f ∫ |X_f'(s)| ds over every yarn, by Gauss quadrature (nq points)."""
    u, w = bspline.gauss(nq)
    total = 0.0
    for f, nseg in enumerate(fab.yarn_nseg):
        s = (np.arange(nseg)[:, None] + u).ravel()
        speed = np.linalg.norm(bspline.curve_points(fab.yarn(f), s, 1), axis=-1)
        total += np.sum(np.tile(w, nseg) * speed)
    return total


def test_yarns_keep_their_own_lengths():
    """Course f of the shaped jersey is 8 c_f + 3 control points; elements
    never straddle two yarns; the joined yarn knits courses 0 and 1."""
    fab = shaped(STITCHES)
    assert np.array_equal(fab.yarn_ncp, 8 * np.array(STITCHES) + 3)
    conn = fab.connectivity(0, fab.nyarn)
    assert len(conn) == np.sum(8 * np.array(STITCHES))
    assert np.all(fab.yarn_of[conn] == fab.yarn_of[conn[:, :1]])
    assert np.array_equal(np.diff(conn, axis=1), np.ones((len(conn), 3)))
    assert np.array_equal(fab.course, fab.yarn_of)
    joined = two_courses_one_yarn(3)
    assert joined.nyarn == 2 and np.array_equal(np.unique(joined.course), [0, 1, 2])
    assert np.array_equal(np.unique(joined.course[joined.yarn_of == 0]), [0, 1])


@pytest.mark.parametrize("size", [1, 2, 3])
def test_layout_splits_whole_yarns_by_control_points(size):
    """Rank boundaries fall on yarn boundaries, the nearest to equal shares;
    yarns of one length split into counts that differ by at most one (on two
    ranks the first takes the odd one)."""
    class Comm:
        rank = 0

    Comm.size = size
    start = np.concatenate([[0], np.cumsum([99, 10, 10, 10, 40, 51])])
    lay = YarnLayout(Comm, start)
    assert lay.yarn_ranges[0] == 0 and lay.yarn_ranges[-1] == 6
    assert np.all(np.diff(lay.yarn_ranges) >= 0)
    share = np.arange(size + 1) * 220 / size
    nearest = np.abs(start[:, None] - share).min(axis=0)
    assert np.array_equal(np.abs(lay.cp_ranges - share), nearest)  # the same subtraction
    for nyarn in (6, 7):
        counts = np.diff(YarnLayout(Comm, np.arange(nyarn + 1) * 11).yarn_ranges)
        assert counts.sum() == nyarn and np.ptp(counts) <= 1
        assert size != 2 or counts[0] == -(-nyarn // 2)


@pytest.mark.parametrize("name", sorted(FABRICS))
def test_mass_is_density_times_rest_length(name):
    """1ᵀ m 1 = ρ L in the full model and, moving the volume rigidly (Γ is a
    partition of unity), tᵀ M^V t = ρ L |t|² in the reduced one."""
    fab = FABRICS[name]()
    rho = 3e-4
    full, red = models(COMM, fab, Material(rho=rho))
    L = COMM.tompi4py().allreduce(full.elements.rest_length())
    # measured up to 1.9e-15 here and below (1 and 2 ranks)
    assert full.total_mass == pytest.approx(rho * L, rel=1e-14, abs=0)
    # the model's 4-point rule against 12 points: 3.3e-6 measured
    assert L == pytest.approx(rest_length(fab), rel=1e-5)
    t = red.rest_state()
    t.getArray().reshape(-1, 3)[:] = [0.0, 1.0, 0.0]
    Mt = t.duplicate()
    red.M.mult(t, Mt)
    assert t.dot(Mt) == pytest.approx(full.total_mass, rel=1e-14, abs=0)


def scene(comm, name, kind, nsteps=3):
    """Held at its top course, ``nsteps`` backward-Euler steps of 1 ms:
    the yarn coordinates at the end, on every rank."""
    full, red = models(comm, FABRICS[name](hold="top"))
    system = {"full": full, "reduced": red}[kind]
    _, x, _ = run(system, BackwardEuler, 1e-3, nsteps)
    return system, gather(comm, system.full_state(x))


@pytest.mark.parametrize("kind", ["full", "reduced"])
@pytest.mark.parametrize("name", sorted(FABRICS))
def test_runs_equal_one_ranks(name, kind):
    """The yarns spread over the ranks (whole yarns, by control points) give
    one rank's motion (under mpirun -n 2; trivially on one rank)."""
    par, xp = scene(COMM, name, kind)
    ser, xs = scene(SELF, name, kind)
    assert np.abs(xs - ser.fabric.X.ravel()).max() > 1e-7            # it moved
    # equal within Newton's tolerance (1e-9 yarn radii a step): measured
    # 1.5e-11 r on 2 ranks (0 on one)
    assert np.allclose(xp, xs, rtol=0, atol=1e-10 * ser.fabric.radius)


@pytest.mark.parametrize("kind", ["full", "reduced", "mixed"])
@pytest.mark.parametrize("name", sorted(FABRICS))
def test_started_turned_strains_nothing(name, kind):
    """Started turned 45° about an oblique axis, free and without gravity,
    the fabric stays at rest: E_el and |g| at round-off after five steps."""
    fab = FABRICS[name]().started_turned(rotation((45, 30, 20)))
    full, red = models(COMM, fab, Material(gravity=0.0), lod=(4, 4))
    system = {"full": full, "reduced": red,
              "mixed": mixed(full, red, region(full, red, [(0, 2, 1, 3)]))}[kind]
    x, energy, worst = steps_from_start(system)
    assert energy < 1e-20 and worst < 1e-12 * fab.radius
    turned = fab.start_points().ravel()
    moved = gather(COMM, system.full_state(x)) - turned
    assert np.abs(moved).max() < 5e-15            # m; 6e-16 measured


@pytest.mark.skipif(COMM.size > 1, reason="one rank's run and files")
def test_output_carries_the_course_of_every_point(tmp_path):
    """The series (meshio's reader) has ``course`` beside ``yarn`` on every
    sample: the joined yarn's samples knit course 0, then 1; the picture and
    the checkpoint of yarns of their own lengths are written."""
    from knitfem.model.full import FullModel
    from knitfem.run.simulation import Simulation

    fab = two_courses_one_yarn(3, hold="top")
    model = FullModel(SELF, fab, Material())
    sim = Simulation(model, BackwardEuler(model, 1e-3), out=str(tmp_path),
                     scene="hanging", verbose=False, output_every=1,
                     snapshots=[0.002], checkpoint_every=1)
    sim.run(0.002)
    sim.close()
    with meshio.xdmf.TimeSeriesReader(str(tmp_path / "yarns.xdmf")) as r:
        points, _ = r.read_points_cells()
        _, data, _ = r.read_data(r.num_steps - 1)
    yarn, course = data["yarn"], data["course"]
    assert len(points) == np.sum(6 * (fab.yarn_ncp - 3) + 1)
    assert np.array_equal(np.unique(course), [0, 1, 2])
    first = course[yarn == 0]
    assert first[0] == 0 and first[-1] == 1 and np.all(np.diff(first) >= 0)
    assert np.all(course[yarn == 1] == 2)
    assert (tmp_path / "checkpoint.h5").exists()
    assert list(tmp_path.glob("*.png"))


def test_yarn_blocks_hold_the_constraints_within_their_yarns():
    """Schwarz blocks of one yarn each: the joined yarn's block holds its
    own courses' interlocks (2 a stitch), the last yarn's its holds; the
    interlocks between the two yarns are in neither."""
    from knitfem.model.full import FullModel

    fab = two_courses_one_yarn(3, hold="top")
    model = FullModel(SELF, fab, Material())
    (c0, r0), (c1, r1) = model.yarn_blocks(1, 0)
    assert len(c0) == 3 * fab.yarn_ncp[0] and len(c1) == 3 * fab.yarn_ncp[1]
    kind = np.repeat(model.constraint_kind, 3)
    assert len(r0) == 3 * 2 * 3 and np.all(kind[r0] == "contact")
    assert len(r1) == 3 * 3 and np.all(kind[r1] == "fixed")
    model.destroy()
