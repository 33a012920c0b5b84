"""The picture worker: the same files as drawing in line, a failed picture
as the run's one-line OutputError, and a dead worker reported, not waited
for."""

import os
import signal
import time

import pytest
from mpi4py import MPI
from petsc4py import PETSc

from helpers import hanging_simulation, jersey
from knitfem import io
from knitfem.run.output import OutputDirectory, OutputError
from knitfem.run.painter import Painter

pytestmark = pytest.mark.skipif(MPI.COMM_WORLD.size > 1,
                                reason="the worker belongs to rank 0")

SELF = PETSc.COMM_SELF


def fabrics():
    """Two poses of a 2x2 swatch and its yarn radius."""
    fab = jersey(2, 2)
    return fab.curves(fab.X), fab.curves(fab.X * [1.0, 0.8, 1.0]), fab.radius


def test_worker_draws_the_files_drawn_in_line(tmp_path):
    P, Q, r = fabrics()
    jobs = [("draw", "a.png", (P, r), dict(title="t = 0.4 s", view="oblique")),
            ("draw_panels", "b.png", ((P, Q), r, ("0", "1")), {}),
            ("animate", "c.gif", ((0.0, 0.1), (P, Q), r), dict(title="x"))]
    painter = Painter()
    for name, path, args, kwargs in jobs:
        painter.submit(name, str(tmp_path / "worker" / path), *args, **kwargs)
        getattr(io, name)(str(tmp_path / "line" / path), *args, **kwargs)
    painter.finish()
    assert painter.proc.returncode is not None
    for _, path, _, _ in jobs:
        drawn = (tmp_path / "worker" / path).read_bytes()
        assert len(drawn) > 1000 and drawn == (tmp_path / "line" / path).read_bytes()


def test_a_failed_picture_is_one_output_error_and_stops_the_drawing(tmp_path):
    P, _, r = fabrics()
    (tmp_path / "taken.png").mkdir()           # a directory where the PNG goes
    out = OutputDirectory(SELF, str(tmp_path))
    painter = Painter()

    def draw():
        for name in ("taken.png", "after.png"):
            painter.submit("draw", str(tmp_path / name), P, r)
        painter.finish()

    with pytest.raises(OutputError, match=r"^cannot write \S+taken\S+: Is a "
                                          r"directory$"):
        out.rank0(draw)
    assert not (tmp_path / "after.png").exists()   # as when drawn in line


def test_a_killed_worker_is_reported_not_waited_for():
    P, _, r = fabrics()
    painter = Painter()
    painter.proc.kill()
    painter.proc.wait()
    painter.submit("draw", "/nonexistent/a.png", P, r)     # no error, no SIGPIPE
    start = time.perf_counter()
    with pytest.raises(OutputError, match=r"^the picture worker \(pid \d+\) was "
                                          r"killed by SIGKILL before it finished; "
                                          r"pictures in /nonexistent may be missing$"):
        painter.finish()
    assert time.perf_counter() - start < 5


def test_the_worker_ignores_ctrl_c(tmp_path, capfd):
    """The terminal sends SIGINT to the worker too: it draws on, quietly."""
    P, _, r = fabrics()
    painter = Painter()
    painter.submit("draw", str(tmp_path / "a.png"), P, r)
    painter.proc.send_signal(signal.SIGINT)
    painter.finish()
    assert (tmp_path / "a.png").stat().st_size > 1000
    assert "Traceback" not in capfd.readouterr().err


def test_a_run_and_its_restart_have_every_picture_after_close(tmp_path):
    fab = jersey(2, 1, hold="top")

    def simulation(out):
        return hanging_simulation(fab, out, output_every=2, checkpoint_every=4,
                                  snapshots=(0.002, 0.006), animation="a.gif")

    pictures = {"hanging_t0.002s.png", "hanging_t0.006s.png",
                "hanging_snapshots.png", "a.gif"}
    whole = simulation(tmp_path / "whole")
    whole.run(0.006)
    assert whole.painter is None                        # finished by close
    assert pictures <= set(os.listdir(tmp_path / "whole"))
    first = simulation(tmp_path / "first")
    first.run(0.004)
    assert {"hanging_t0.002s.png", "hanging_snapshots.png"} <= set(
        os.listdir(tmp_path / "first"))
    again = simulation(tmp_path / "again")
    again.restart(str(tmp_path / "first" / "checkpoint.h5"))
    again.run(0.006)               # its GIF: frames after the restart, one here
    assert pictures - {"a.gif"} <= set(os.listdir(tmp_path / "again"))
    for name in ("hanging_t0.002s.png", "hanging_t0.006s.png",
                 "hanging_snapshots.png"):         # the restart is exact
        assert ((tmp_path / "again" / name).read_bytes()
                == (tmp_path / "whole" / name).read_bytes())


def test_the_pictures_show_the_moving_bodies_where_they_were_at_each_frame(
        tmp_path, monkeypatch):
    """The snapshots, their panel and the animation of a sleeve whose elbow
    bends get each frame's bodies: the forearm along +z at t = 0 and turned
    at the end as summary.json gives it, not the end pose in every frame."""
    import numpy as np

    from knitfem import api
    from knitfem.run.simulation import Simulation

    jobs = {}
    monkeypatch.setattr(Simulation, "paint",
                        lambda self, name, *a, **k: jobs.setdefault(name, []).append(k))
    fabric = api.scene("sleeve", rows=4, cols=8, elbow_angle=30, elbow_time=0.02,
                       friction=0)
    sim = api.simulation(api.reduced_model(fabric), out=str(tmp_path), scene="sleeve",
                         snapshots=(0.0, 0.02), animation="sleeve.gif", output_every=1)
    fore = sim.run(0.02)["bodies"][1]
    shots = [k["bodies"] for k in jobs["draw"]]
    panel, movie = jobs["draw_panels"][0]["bodies"], jobs["animate"][0]["bodies"]
    assert len(panel) == len(shots) == 2 and len(movie) == 3
    for frames in (shots, panel, movie):
        start, end = frames[0][1].b, frames[-1][1].b      # the forearm's tip
        assert start[1] == 0 < start[2]                   # along +z, at rest
        assert np.array_equal(end, fore["p1"])            # turned, as summarised
    tips = np.array([b[1].b for b in movie])
    assert 0 == tips[0, 1] < tips[1, 1] < tips[2, 1]      # turning frame by frame
