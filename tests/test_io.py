"""The time series as meshio reads it back: every frame, moving points."""

import meshio
import numpy as np
import pytest
from mpi4py import MPI

from knitfem import io
from helpers import jersey

pytestmark = pytest.mark.skipif(MPI.COMM_WORLD.rank > 0, reason="files on rank 0")


def read(path):
    with meshio.xdmf.TimeSeriesReader(path) as r:
        points, cells = r.read_points_cells()
        frames = [r.read_data(k) for k in range(r.num_steps)]
    return points, cells, frames


def moved(P, k):
    """Frame k: the fabric translated and sheared (every point moves)."""
    X = P.points
    return P.moved(X + k * np.array([0.0, -1e-3, 2e-4]) + 1e-3 * k * X[:, :1])


def curves(fab):
    return fab.curves(fab.X)


def test_meshio_reads_every_frame_with_its_geometry(tmp_path):
    P = curves(jersey(2, 2))
    s = io.CentrelineSeries(str(tmp_path / "yarns.xdmf"), P, 5e-4)
    for k in range(3):
        s.write(10 * k, 0.1 * k, moved(P, k))
    points, cells, frames = read(tmp_path / "yarns.xdmf")
    assert [t for t, _, _ in frames] == [0.0, 0.1, 0.2]
    assert cells[0].type == "line" and np.array_equal(points, io.centrelines(P)
                                                      .points)
    for k, (_, data, _) in enumerate(frames):
        expect = io.centrelines(moved(P, k)).points
        assert np.array_equal(data["position"], expect)
        assert np.all(data["radius"] == 5e-4)


def test_series_continued_keeps_frames_up_to_the_checkpoint(tmp_path):
    P = curves(jersey(2, 2))
    path = str(tmp_path / "yarns.xdmf")
    s = io.CentrelineSeries(path, P, 5e-4)
    for k in range(4):
        s.write(k, 0.01 * k, moved(P, k))
    s = io.CentrelineSeries(path, P, 5e-4, keep=1, note="continues x")
    s.write(2, 0.02, moved(P, 5))
    _, _, frames = read(path)
    assert [t for t, _, _ in frames] == [0.0, 0.01, 0.02]
    assert np.array_equal(frames[1][1]["position"],
                          io.centrelines(moved(P, 1)).points)
    assert np.array_equal(frames[2][1]["position"],
                          io.centrelines(moved(P, 5)).points)
    assert sorted(p.name for p in (tmp_path / "yarns").iterdir()) == [
        "00000000.h5", "00000001.h5", "00000002.h5", "mesh.h5"]
    assert 'Value="continues x"' in open(path).read()
    io.CentrelineSeries(path, P, 5e-4)                   # a fresh series
    assert [p.name for p in (tmp_path / "yarns").iterdir()] == ["mesh.h5"]
    assert "<Time" not in open(path).read()


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="runs a subprocess")
def test_a_full_disk_is_one_oserror_and_a_clean_exit():
    """HDF5 output to a device with no space left (/dev/full): one OSError
    (ENOSPC), nothing reported by h5py's destructors, a normal exit."""
    import subprocess
    import sys

    code = ("import errno, numpy as np\n"
            "from knitfem import io\n"
            "try:\n"
            "    io.write_hdf5('/dev/full', lambda f: f.create_dataset('x', data=np.ones(10**5)))\n"
            "except OSError as e:\n"
            "    assert e.errno == errno.ENOSPC\n"
            "    print('ENOSPC')\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 0 and p.stdout == "ENOSPC\n" and p.stderr == "", p.stderr


@pytest.mark.parametrize("view", ["front", "three_quarter"])
def test_tubes_are_drawn_one_yarn_diameter_wide(tmp_path, view):
    """After the layout is final, every tube's line width in points is its
    diameter (2r, and 1.15 × 2r for the outline) at the axes' scale."""
    import matplotlib.pyplot as plt

    P = curves(jersey(3, 2))
    radius = 5e-4
    fig, ax = plt.subplots(figsize=(8, 3), dpi=110)
    io._draw_on(ax, P, radius, view, None)
    fig.tight_layout()
    io._fit_widths(fig)
    fig.canvas.draw()
    (x0, _), (x1, _) = ax.transData.transform([(0, 0), (1, 0)])
    points = 2 * radius * (x1 - x0) * 72 / fig.dpi
    widths = sorted(c.get_linewidth()[0] for c in ax.collections)
    plt.close(fig)
    # measured 1.5e-16
    assert widths == pytest.approx([points, 1.15 * points], rel=5e-15, abs=0)
