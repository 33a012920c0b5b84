"""The yarns as tube meshes for renderers (``yarn.tubes``, ``io.TubeFrames``,
``-knit_tube_mesh``): exact prisms on straight yarns, closed and outward
surfaces, parallel-transported frames, files meshio reads back, and one file
a frame of a run, around the samples of its time series."""

import glob
import os
import shutil
import subprocess

import h5py
import meshio
import numpy as np
import pytest
from mpi4py import MPI

from benchmarks.doc_commands import ROOT, commands_in, environment
from helpers import jersey
from knitfem import io
from knitfem.yarn.curves import Samples
from knitfem.yarn.tubes import SIDES, tube_mesh, yarn_colours

pytestmark = pytest.mark.skipif(MPI.COMM_WORLD.size > 1,
                                reason="one process; runs mpirun itself")

K = SIDES


def samples(*yarns):
    """``Samples`` of the yarns given as (n, 3) point arrays."""
    start = np.concatenate([[0], np.cumsum([len(y) for y in yarns])])
    yarn = np.repeat(np.arange(len(yarns)), np.diff(start))
    return Samples(np.concatenate(yarns), start, yarn, np.zeros_like(yarn))


def volume(points, triangles):
    """Σ det(a, b, c) / 6 over the triangles: the enclosed volume of a closed
    surface oriented outward (negative if inward)."""
    a, b, c = np.moveaxis(points[triangles], 1, 0)
    return np.einsum("ti,ti->t", a, np.cross(b, c)).sum() / 6


def edge_uses(triangles):
    """How often each directed edge occurs, and each undirected one."""
    e = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]],
                        triangles[:, [2, 0]]])
    directed = np.unique(e, axis=0, return_counts=True)[1]
    undirected = np.unique(np.sort(e, axis=1), axis=0, return_counts=True)[1]
    return directed, undirected


def straight(n, length, origin, direction):
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    return np.asarray(origin) + np.linspace(0, length, n)[:, None] * d


def helix(n, turns=1.5, radius=1.0, pitch=0.4):
    a = np.linspace(0, 2 * np.pi * turns, n)
    return np.c_[radius * np.cos(a), radius * np.sin(a), pitch * a]


POLYGON = K / (2 * np.pi) * np.sin(2 * np.pi / K)
"""Area of the regular k-gon inscribed in a circle, in units of the circle's."""


def test_straight_yarn_is_a_capped_prism_of_radius_r():
    """A straight yarn of n samples along an oblique axis: k n vertices at
    distance r from the axis (measured 1.2e-15 r), 2 k (n − 1) side triangles
    and k − 2 at each end, enclosing π r² L times the k-gon's factor
    (k / 2π) sin(2π / k) (measured 2.2e-16 relative)."""
    n, r, length = 7, 0.1, 2.0
    origin, d = np.array([0.3, -0.2, 0.5]), np.array([1.0, 2.0, -0.5])
    m = tube_mesh(samples(straight(n, length, origin, d)), False, r)
    assert m.points.shape == (K * n, 3)
    d /= np.linalg.norm(d)
    off = m.points - origin
    dist = np.linalg.norm(off - (off @ d)[:, None] * d, axis=1)
    assert np.abs(dist - r).max() < 1e-14 * r
    spans = np.ptp(m.triangles // K, axis=1)          # rings a triangle spans
    assert len(m.triangles) == 2 * K * (n - 1) + 2 * (K - 2)
    assert np.count_nonzero(spans == 1) == 2 * K * (n - 1)
    assert volume(m.points, m.triangles) == pytest.approx(  # measured 2.5e-16
        np.pi * r**2 * length * POLYGON, rel=2e-15, abs=0)
    assert np.allclose(np.linalg.norm(m.normals, axis=1), 1, rtol=0, atol=2e-15)


def test_open_and_closed_yarns_are_closed_outward_surfaces():
    """An open helix and a closed circle in one mesh: every directed edge
    once and every edge in two triangles (a closed, consistently oriented
    surface), each yarn's vertices tagged by its index; the ring of a closed
    yarn of n samples (its last repeats its first) makes 2 k (n − 1)
    triangles. Its N = n − 1 rings, the same k-gon turned about the circle's
    axis by δ = 2π/N, bound pieces made of the chords from each point of
    the k-gon (at distance ρ from the axis) to its turned image, 2ρ sin(δ/2)
    long at cos(δ/2) to the k-gon's plane: a piece holds sin δ ∫ρ dA =
    sin δ R A_k, the ring N R sin δ A_k, Pappus' 2π R A_k with the N-gon's
    factor (measured 3.3e-16 relative)."""
    n, R, r = 61, 1.0, 0.05
    a = np.linspace(0, 2 * np.pi, n)
    circle = np.c_[R * np.cos(a), R * np.sin(a), np.zeros(n)]
    circle[-1] = circle[0]
    m = tube_mesh(samples(helix(40), circle), [False, True], r)
    directed, undirected = edge_uses(m.triangles)
    assert (directed == 1).all() and (undirected == 2).all()
    assert np.array_equal(m.yarn, np.repeat([0, 1], [K * 40, K * (n - 1)]))
    ring = tube_mesh(samples(circle), True, r)
    assert len(ring.triangles) == 2 * K * (n - 1)
    exact = (n - 1) * R * np.sin(2 * np.pi / (n - 1)) * np.pi * r**2 * POLYGON
    # measured 4.7e-16
    assert volume(ring.points, ring.triangles) == pytest.approx(exact, rel=3e-15, abs=0)
    assert volume(m.points, m.triangles) > 0


def test_frames_are_parallel_transported():
    """Along an open helix each ring's first normal u_i is R_i u_{i−1}, the
    smallest rotation taking the tangent t_{i−1} to t_i applied to the one
    before (a loop here; measured 3.3e-16), and each ring is centred on its
    sample (the k-gon's vertices sum to zero; measured 4.4e-16)."""
    x = helix(50)
    m = tube_mesh(samples(x), False, 0.1)
    u = m.normals[::K]
    t = np.gradient(x, axis=0)          # central differences, one-sided at ends
    t[1:-1] = x[2:] - x[:-2]
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    for i in range(1, len(x)):
        moved = u[i - 1] - (u[i - 1] @ t[i]) / (1 + t[i - 1] @ t[i]) * (t[i - 1] + t[i])
        assert np.abs(moved - u[i]).max() < 3e-15
    assert np.abs(m.points.reshape(-1, K, 3).mean(axis=1) - x).max() < 3e-15


def test_closed_yarn_frame_closes_with_a_uniform_twist():
    """A closed non-planar loop: the frame is parallel transport but for a
    uniform twist that takes out the holonomy, so the turn from each ring to
    the next about its tangent, relative to transport, is that twist times
    the step's length (measured 3.3e-15 rad/m), wrap step included."""
    n = 80
    a = np.linspace(0, 2 * np.pi, n + 1)
    x = np.c_[np.cos(a), np.sin(a), 0.5 * np.sin(2 * a)]
    x[-1] = x[0]
    m = tube_mesh(samples(x), True, 0.02)
    x = x[:-1]
    u = m.normals[::K]
    t = np.roll(x, -1, axis=0) - np.roll(x, 1, axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    nxt = np.roll(np.arange(n), -1)
    moved = u - np.sum(u * t[nxt], axis=1)[:, None] / (
        1 + np.sum(t * t[nxt], axis=1))[:, None] * (t + t[nxt])
    turn = np.arctan2(np.sum(np.cross(moved, u[nxt]) * t[nxt], axis=1),
                      np.sum(moved * u[nxt], axis=1))
    step = np.linalg.norm(x[nxt] - x, axis=1)
    rate = turn / step
    assert np.abs(rate - rate.mean()).max() < 3e-14
    assert abs(rate.mean()) * step.sum() <= np.pi


def test_meshio_reads_the_frames_back(tmp_path):
    """PLY, OBJ and OFF frames of a 2x2 jersey read back by meshio with the
    same triangles and points; PLY with each vertex's yarn and its yarn's
    colour as uint8 red, green, blue (Blender's vertex colours)."""
    fab = jersey(2, 2)
    P = fab.curves(fab.X)
    m = tube_mesh(io.centrelines(P), fab.closed, fab.radius)
    for fmt in io.TUBE_FORMATS:
        frames = io.TubeFrames(str(tmp_path / fmt), fmt, fab.closed, fab.radius)
        frames.write(7, P)
        back = meshio.read(tmp_path / fmt / f"00000007.{fmt}")
        assert np.array_equal(back.cells_dict["triangle"], m.triangles)
        # binary doubles (PLY) or their shortest repr (OBJ, OFF): exact
        assert np.array_equal(back.points, m.points)
    data = meshio.read(tmp_path / "ply" / "00000007.ply").point_data
    assert np.array_equal(data["yarn"], m.yarn)
    rgb = np.stack([data[c] for c in ("red", "green", "blue")], axis=1)
    assert rgb.dtype == np.uint8
    assert np.array_equal(rgb, yarn_colours(P.nyarn)[m.yarn])
    assert len({tuple(c) for c in yarn_colours(P.nyarn)}) == P.nyarn


def test_frames_after_a_restart_step_are_removed(tmp_path):
    """A restart into the directory keeps the frames up to its checkpoint's
    step and removes the later ones and temporaries; a new series (or a run
    without tube meshes) removes every frame, of any format."""
    fab = jersey(2, 2)
    P = fab.curves(fab.X)
    d = str(tmp_path / "tubes")
    frames = io.TubeFrames(d, "ply", fab.closed, fab.radius)
    for step in (0, 10, 20):
        frames.write(step, P)
    (tmp_path / "tubes" / ".00000030.host.1.tmp.ply").write_text("")
    io.TubeFrames(d, "off", fab.closed, fab.radius, keep=10).write(11, P)
    assert sorted(os.listdir(d)) == ["00000000.ply", "00000010.ply", "00000011.off"]
    io.TubeFrames.remove(d)
    assert os.listdir(d) == []


def test_run_writes_one_tube_mesh_a_frame_around_the_series(tmp_path):
    """The command docs/guide/output.md shows, run as written: -knit_tube_mesh
    ply writes one PLY file per frame of the XDMF series, named by its step,
    whose rings are centred on that frame's centreline samples (measured
    1.7e-18 m); a new run with -knit_tube_mesh none into the same directory
    leaves no tube files there."""
    text = open(os.path.join(ROOT, "docs", "guide", "output.md")).read()
    command = next(c for c in commands_in(text) if "-knit_tube_mesh" in c)
    p = subprocess.run(command.split() + ["-skip_petscrc"], capture_output=True,
                       text=True, env=environment(), cwd=tmp_path, timeout=300)
    assert p.returncode == 0, p.stdout + p.stderr
    out = tmp_path / command.split("-o ")[1].split()[0]
    steps = sorted(os.path.basename(f) for f in glob.glob(str(out / "yarns" / "0*.h5")))
    tubes = sorted(os.path.basename(f) for f in glob.glob(str(out / "tubes" / "*")))
    assert len(steps) > 2 and tubes == [s.replace(".h5", ".ply") for s in steps]
    for name in (steps[0], steps[-1]):
        with h5py.File(out / "yarns" / name) as f:
            centres = f["geometry"][...]
        mesh = meshio.read(out / "tubes" / name.replace(".h5", ".ply"))
        ring = mesh.points.reshape(-1, K, 3).mean(axis=1)
        assert ring.shape == centres.shape and np.abs(ring - centres).max() < 1e-17
    words = command.replace("-knit_tube_mesh ply", "-knit_tube_mesh none").split()
    p = subprocess.run(words + ["-knit_t_end", "0.002", "-skip_petscrc"],
                       capture_output=True, text=True, env=environment(),
                       cwd=tmp_path, timeout=300)
    assert p.returncode == 0, p.stdout + p.stderr
    assert not os.path.exists(out / "tubes") or not os.listdir(out / "tubes")


def test_a_restart_continues_the_tube_frames(tmp_path):
    """A run continued from its earlier checkpoint into its own directory
    keeps the tube frames up to the checkpoint's step (the same files) and
    writes the later ones again: one tube frame for every frame of the
    series, each around it."""
    out = tmp_path / "r"
    run = ["knitfem", "run", "-knit_rows", "2", "-knit_cols", "2", "-knit_snapshots",
           "", "-knit_integrator", "implicit", "-knit_dt", "1e-3", "-knit_t_end",
           "0.01", "-knit_output_every", "1", "-knit_checkpoint_every", "5",
           "-knit_tube_mesh", "ply", "-o", str(out), "-skip_petscrc"]
    p = subprocess.run(run, capture_output=True, text=True, env=environment(),
                       timeout=300)
    assert p.returncode == 0, p.stdout + p.stderr
    with h5py.File(out / "checkpoint.prev.h5") as f:
        step = int(f.attrs["step"])
    before = {n: os.stat(out / "tubes" / n).st_mtime_ns
              for n in os.listdir(out / "tubes")}
    p = subprocess.run(run + ["-knit_restart", str(out / "checkpoint.prev.h5")],
                       capture_output=True, text=True, env=environment(), timeout=300)
    assert p.returncode == 0, p.stdout + p.stderr
    after = {n: os.stat(out / "tubes" / n).st_mtime_ns
             for n in os.listdir(out / "tubes")}
    assert 0 < step < 10 and sorted(after) == sorted(before)
    assert all((after[n] == before[n]) == (int(n[:8]) <= step) for n in after)
    frames = sorted(os.listdir(out / "yarns"))
    assert sorted(after) == [n.replace(".h5", ".ply") for n in frames if n[0] == "0"]
    for name in after:
        with h5py.File(out / "yarns" / name.replace(".ply", ".h5")) as f:
            centres = f["geometry"][...]
        ring = meshio.read(out / "tubes" / name).points.reshape(-1, K, 3).mean(axis=1)
        assert np.abs(ring - centres).max() < 1e-17


@pytest.mark.skipif(shutil.which("mpirun") is None, reason="no mpirun")
def test_two_ranks_write_the_frames_of_one(tmp_path):
    """Under mpirun -n 2 rank 0 writes the gathered yarns: the same files,
    triangles, yarns and colours as one rank, the points within the states'
    difference (measured 1.4e-12 m in 0.02 s, Newton's tolerance)."""
    run = ["knitfem", "run", "-knit_rows", "2", "-knit_cols", "2", "-knit_snapshots",
           "", "-knit_t_end", "0.02", "-knit_tube_mesh", "ply", "-skip_petscrc"]
    for out, head in (("one", []), ("two", ["mpirun", "-n", "2"])):
        p = subprocess.run(head + run + ["-o", str(tmp_path / out)], text=True,
                           capture_output=True, env=environment(), timeout=300)
        assert p.returncode == 0, p.stdout + p.stderr
    names = sorted(os.listdir(tmp_path / "one" / "tubes"))
    assert len(names) > 2 and names == sorted(os.listdir(tmp_path / "two" / "tubes"))
    for name in names:
        one, two = (meshio.read(tmp_path / d / "tubes" / name) for d in ("one", "two"))
        assert np.array_equal(one.cells_dict["triangle"], two.cells_dict["triangle"])
        assert all(np.array_equal(one.point_data[k], two.point_data[k])
                   for k in ("yarn", "red", "green", "blue"))
        assert np.abs(one.points - two.points).max() < 1e-11


def test_an_unknown_tube_format_is_refused_in_one_line(tmp_path):
    """A format meshio writes but -knit_tube_mesh does not offer: one line
    naming the option and the formats it accepts, before anything runs."""
    p = subprocess.run(["knitfem", "run", "-knit_tube_mesh", "stl", "-o",
                        str(tmp_path / "a"), "-skip_petscrc"], capture_output=True,
                       text=True, env=environment(), timeout=300)
    assert p.returncode != 0
    assert p.stderr.strip().splitlines()[-1] == ("knitfem run: error: -knit_tube_mesh "
                                                 "'stl': expected one of none, ply, "
                                                 "obj, off")
    assert not (tmp_path / "a").exists()
