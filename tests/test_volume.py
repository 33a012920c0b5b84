"""Bounding volume V and the stitches-fitting rows Γ̃ (knitfem.lod.volume).

Γ̃ must be exact: its rows are a partition of unity, so it reproduces affine
maps of the control net to rounding; Newton inversion of the volume map is
checked against known parameters; the imposed deformations against their
closed forms.

meshes/volume_5x5x2.vtu is the paper's 5×5×2 net: the `around` box of the
control points of a flat 15 × 30 jersey (pattern.Jersey(15, 30) defaults),
with a margin of one yarn radius. It was written by

    from knitfem.knit.pattern import Jersey
    from knitfem.lod.volume import BoundingVolume
    j = Jersey(15, 30)
    BoundingVolume.around(j.all_control_points(), 5, 5, j.radius).save(
        "meshes/volume_5x5x2.vtu")
"""

from pathlib import Path

import meshio
import numpy as np
import pytest

from knitfem.yarn import bspline
from knitfem.lod.volume import DEFAULT_AMOUNTS, BoundingVolume

MESHES = Path(__file__).resolve().parent.parent / "meshes"


def cloud(seed=0, n=200):
    """Random points in a 3 × 2 × 0.3 slab, like a small fabric."""
    return np.random.default_rng(seed).random((n, 3)) * [3.0, 2.0, 0.3]


def box(n1=5, n2=5, seed=0):
    return BoundingVolume.around(cloud(seed), n1, n2, margin=0.05)


def random_parameters(V, n=500, seed=1):
    """(n, 3) parameters in the domain, with some on its faces."""
    t = np.random.default_rng(seed).random((n, 3)) * V.domain
    t[:10] = np.round(t[:10] / V.domain) * V.domain
    return t


def fit(V, cols, vals):
    """Stitches fitting ε = Γ̃ q with the net of V."""
    return np.einsum("nc,nci->ni", vals, V.flat[cols])


def perturbed(n1=6, n2=5, seed=2):
    """A general (curved, uneven) volume: a box with jittered control points."""
    V = box(n1, n2)
    h = (V.flat.max(0) - V.flat.min(0)) / [n1 - 1, n2 - 1, 1]
    dq = 0.15 * h * np.random.default_rng(seed).uniform(-1, 1, V.flat.shape)
    return BoundingVolume.from_flat(V.flat + dq, n1, n2)


def test_numbering_and_flat_view():
    V = perturbed()
    k1, k2, k3 = 3, 2, 1
    k = V.index(k1, k2, k3)
    assert k == k1 + V.n1 * (k2 + V.n2 * k3)
    assert np.array_equal(V.flat[k], V.net[k3, k2, k1])
    assert V.flat.shape == (V.size, 3) and np.shares_memory(V.flat, V.net)


def test_weights_are_a_partition_of_unity():
    V = perturbed()
    t = random_parameters(V)
    cols, vals = V.weights(*t.T)
    assert cols.shape == vals.shape == (len(t), 32)
    assert np.all(vals >= -1e-15)
    assert np.allclose(vals.sum(axis=1), 1.0, rtol=0, atol=3e-15)  # measured 2.2e-16
    assert cols.min() >= 0 and cols.max() < V.size
    assert all(len(np.unique(row)) == 32 for row in cols[:20])
    # measured 0 (points up to 3.0)
    assert np.allclose(fit(V, cols, vals), V.points(*t.T), rtol=0, atol=2e-15)


def test_jacobian_matches_finite_differences():
    V = perturbed()
    t = random_parameters(V, n=50)[10:]
    J = V.jacobian(*t.T)
    h = 1e-6
    for c in range(3):
        e = np.eye(3)[c] * h
        fd = (V.points(*(t + e).T) - V.points(*(t - e).T)) / (2 * h)
        assert np.allclose(J[..., c], fd, rtol=0, atol=1e-8)


def test_around_is_affine_and_encloses():
    pts = cloud()
    V = BoundingVolume.around(pts, 6, 5, margin=0.05)
    lo, hi = pts.min(0) - 0.05, pts.max(0) + 0.05
    s1, s2, w3 = V.embed(pts)
    expected = (pts - lo) / (hi - lo) * V.domain
    # measured 1.3e-15
    assert np.allclose(np.stack([s1, s2, w3], -1), expected, rtol=0, atol=2e-14)
    corners = V.points([0, V.domain[0]], [0, V.domain[1]], [0, 1])
    assert np.allclose(corners, [lo, hi], rtol=0, atol=7e-15)  # measured 4.4e-16


def test_fitting_reproduces_points_and_affine_maps():
    V = box(6, 5)
    x = V.points(*random_parameters(V).T)
    cols, vals = V.weights(*V.embed(x))
    assert np.allclose(fit(V, cols, vals), x, rtol=0, atol=2e-14)  # measured 1.3e-15
    rng = np.random.default_rng(3)
    A = np.eye(3) + 0.4 * rng.uniform(-1, 1, (3, 3))
    b = rng.uniform(-1, 1, 3)
    moved = BoundingVolume.from_flat(V.flat @ A.T + b, V.n1, V.n2)
    # measured 1.1e-15
    assert np.allclose(fit(moved, cols, vals), x @ A.T + b, rtol=0, atol=2e-14)


@pytest.mark.parametrize("make", [
    lambda: box().deformed("flexion"),
    lambda: box(7, 5).deformed("torsion", 120),
    lambda: box().deformed("shear").deformed("torsion"),
    perturbed,
])
def test_embed_inverts_points_on_curved_volumes(make):
    V = make()
    t = random_parameters(V, n=2000)
    s = V.embed(V.points(*t.T))
    assert np.allclose(np.stack(s, -1), t, rtol=0, atol=4e-14)  # measured 3.2e-15


@pytest.mark.parametrize("x", [[1.5, 1.0, 0.4], [3.2, 1.0, 0.1], [1e3, -1e3, 5.0]])
def test_point_outside_raises(x):
    V = box()
    inside = V.points(1.0, 1.0, 0.5)
    with pytest.raises(ValueError, match="1 of 2 points lie outside"):
        V.embed([inside, x])
    with pytest.raises(ValueError, match="outside"):
        V.deformed("torsion").embed([x])


def test_traction_scales_x_distances():
    V = box()
    x = V.points(*random_parameters(V).T)
    cols, vals = V.weights(*V.embed(x))
    y = fit(V.deformed("traction", 1.2), cols, vals)
    dx, dy = x[1:] - x[0], y[1:] - y[0]
    assert np.allclose(dy[:, 0], 1.2 * dx[:, 0], rtol=0, atol=3e-14)  # measured 2.4e-15
    assert np.allclose(y[:, 1:], x[:, 1:], rtol=0, atol=9e-15)  # measured 8.9e-16


def test_shear_moves_x_by_tan_angle_times_y():
    V = box()
    yc = 0.5 * (V.flat[:, 1].min() + V.flat[:, 1].max())
    x = V.points(*random_parameters(V).T)
    cols, vals = V.weights(*V.embed(x))
    y = fit(V.deformed("shear", 30), cols, vals)
    shift = np.tan(np.radians(30)) * (x[:, 1] - yc)
    assert np.allclose(y[:, 0], x[:, 0] + shift, rtol=0, atol=3e-14)  # measured 2.2e-15
    assert np.allclose(y[:, 1:], x[:, 1:], rtol=0, atol=9e-15)  # measured 8.9e-16


def centre_and_length(V):
    lo, hi = V.flat.min(0), V.flat.max(0)
    return 0.5 * (lo + hi), (hi[0] - lo[0]) * (V.n1 - 3) / (V.n1 - 1)


@pytest.mark.parametrize("n1, tol", [(5, 2e-3), (7, 1.5e-4)])
def test_torsion_keeps_distance_to_axis(n1, tol):
    V = box(n1, 5)
    c, L = centre_and_length(V)
    W = V.deformed("torsion", 90)
    rng = np.random.default_rng(4)
    t = random_parameters(V)
    t[:250, 0] = rng.integers(0, n1 - 2, 250)        # junctions s₁ ∈ ℤ: exact
    x, y = V.points(*t.T), W.points(*t.T)
    assert np.array_equal(y[:, 0], x[:, 0])   # the twist leaves the nets' x as they are
    th = np.radians(90) * (x[:, 0] - c[0]) / L
    rot = np.stack([np.cos(th), -np.sin(th), np.sin(th), np.cos(th)], -1)
    ideal = c[1:] + np.einsum("nij,nj->ni", rot.reshape(-1, 2, 2), x[:, 1:] - c[1:])
    assert np.allclose(y[:250, 1:], ideal[:250], rtol=0, atol=2e-14)  # measured 1.1e-15
    r0, r = (np.linalg.norm(p[:, 1:] - c[1:], axis=-1) for p in (x, y))
    assert np.allclose(r, r0, rtol=tol, atol=0)


@pytest.mark.parametrize("n1, tol", [(5, 1e-3), (7, 6e-5)])
def test_flexion_bends_rows_into_arcs_of_kept_length(n1, tol):
    V = box(n1, 5)
    c, L = centre_and_length(V)
    W = V.deformed("flexion", 90)
    R = L / np.radians(90)
    # at junctions s₁ ∈ ℤ every point sits on its ideal arc
    t = random_parameters(V)
    t[:, 0] = np.random.default_rng(5).integers(0, n1 - 2, len(t))
    x, y = V.points(*t.T), W.points(*t.T)
    xi, zeta = x[:, 0] - c[0], x[:, 2] - c[2]
    ideal = np.stack([c[0] + (R - zeta) * np.sin(xi / R), x[:, 1],
                      c[2] + R - (R - zeta) * np.cos(xi / R)], -1)
    assert np.allclose(y, ideal, rtol=0, atol=3e-14)  # measured 2.2e-15
    # the mid-surface keeps its length along x, and its ends turn by 90°
    q, w = bspline.gauss(8)
    s1 = (np.arange(n1 - 3)[:, None] + q).ravel()
    for s2 in (0.0, 1.3, 2.0):
        speed = np.linalg.norm(W.jacobian(s1, s2, 0.5)[..., 0], axis=-1)
        length = np.sum(speed * np.tile(w, n1 - 3))
        assert abs(length / L - 1) < tol
        ends = W.jacobian([0, n1 - 3], s2, 0.5)[..., 0]
        assert abs(np.dot(*ends)) < 2e-16 * L * L      # measured 1.2e-17 L²


def test_default_amounts_and_unknown_mode():
    V = box()
    assert set(DEFAULT_AMOUNTS) == {"flexion", "traction", "shear", "torsion"}
    for mode in DEFAULT_AMOUNTS:
        assert V.deformed(mode).net.shape == V.net.shape
    with pytest.raises(ValueError, match="flexion, traction, shear, torsion"):
        V.deformed("bend")


def test_bad_nets_are_refused():
    with pytest.raises(ValueError, match="n1, n2 >= 4"):
        BoundingVolume(np.zeros((2, 5, 3, 3)))
    with pytest.raises(ValueError, match=r"shape \(2, n2, n1, 3\)"):
        BoundingVolume(np.zeros((3, 5, 5, 3)))
    with pytest.raises(ValueError, match="no volume along z"):
        BoundingVolume.around(np.c_[np.random.rand(9, 2), np.zeros(9)], 5, 5)


@pytest.mark.parametrize("suffix", [".vtu", ".xdmf"])
def test_save_load_round_trip(tmp_path, suffix):
    V = perturbed().deformed("torsion")
    V.save(tmp_path / f"v{suffix}")
    U = BoundingVolume.load(tmp_path / f"v{suffix}")
    assert (U.n1, U.n2) == (V.n1, V.n2)
    assert np.array_equal(U.net, V.net)
    mesh = meshio.read(tmp_path / f"v{suffix}")
    assert mesh.cells[0].type == "hexahedron"
    assert mesh.cells[0].data.shape == ((V.n1 - 1) * (V.n2 - 1), 8)


def test_malformed_files_are_refused(tmp_path):
    box().save(tmp_path / "good.vtu")
    mesh = meshio.read(tmp_path / "good.vtu")
    pts, lattice = mesh.points, mesh.point_data["lattice_index"]

    def write(name, points, data):
        cells = [("vertex", np.arange(len(points))[:, None])]
        meshio.Mesh(points, cells, point_data=data).write(tmp_path / name)
        return tmp_path / name

    with pytest.raises(ValueError, match="no 'lattice_index' point data"):
        BoundingVolume.load(write("bare.vtu", pts, {}))
    keep = np.arange(len(pts)) != 7
    with pytest.raises(ValueError, match="49 points, expected"):
        BoundingVolume.load(write("short.vtu", pts[keep],
                                  {"lattice_index": lattice[keep]}))
    with pytest.raises(ValueError, match="numbering"):
        BoundingVolume.load(write("rev.vtu", pts[::-1],
                                  {"lattice_index": lattice[::-1]}))
    (tmp_path / "junk.vtu").write_text("<VTKFile garbage")
    with pytest.raises(ValueError, match="not a readable"):
        BoundingVolume.load(tmp_path / "junk.vtu")
    with pytest.raises(ValueError, match="use one of"):
        BoundingVolume.load(tmp_path / "good.stl")


def test_example_volume_encloses_the_15x30_jersey():
    pattern = pytest.importorskip("knitfem.knit.pattern")
    V = BoundingVolume.load(MESHES / "volume_5x5x2.vtu")
    assert (V.n1, V.n2, V.size) == (5, 5, 50)
    jersey = pattern.Jersey(15, 30)
    P = jersey.all_control_points()
    cols, vals = V.weights(*V.embed(P))
    assert np.allclose(fit(V, cols, vals), P, rtol=0, atol=1e-15)
    expected = BoundingVolume.around(P, 5, 5, jersey.radius)
    # measured 0 (4.3e-19 before)
    assert np.allclose(V.net, expected.net, rtol=0, atol=1e-15 * np.abs(V.net).max()), (
        "meshes/volume_5x5x2.vtu is stale; regenerate it (see module docstring)")
