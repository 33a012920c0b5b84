"""Textile measures (``knitfem.knit.measure``) on knits whose answer is known."""

import numpy as np
import pytest

from knitfem.knit.measure import (EDGES, curl, loop_length, munden, spacings,
                                  surface_normals, turned)
from knitfem.knit.pattern import Jersey
from knitfem.yarn import bspline


def grid(rows, cols, cs=3e-3, ws=4e-3):
    """Loop heads of a flat swatch in the x–y plane."""
    r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    return np.stack([c * ws, r * cs, np.zeros_like(r, dtype=float)], axis=-1)


def test_a_flat_grid_has_its_spacings_and_no_curl():
    H = grid(8, 6)
    assert spacings(H) == pytest.approx((3e-3, 4e-3), rel=2e-15, abs=0)  # measured 2.9e-16
    edges = curl(H, back=(0, 0, 1), radius=5e-4)
    assert all(edges[e]["side"] == "flat" for e in EDGES)


def test_munden_constants_are_length_ratios():
    assert munden(16.8e-3, 3e-3, 4.2e-3) == pytest.approx((5.6, 4.0, 22.4), rel=1e-15,
                                                         abs=0)  # measured 0


def test_curl_sides_of_a_curled_jersey():
    """Courses' ends rolled to the face (−z), first and last courses to the
    back (+z): the sides, and the sign and angle of the offsets."""
    H = grid(12, 12)
    x = H[..., 0] - H[..., 0].mean()
    y = H[..., 1] - H[..., 1].mean()
    H[..., 2] = -30.0 * x**2 * (np.abs(x) > 0.012) + 40.0 * y**2 * (np.abs(y) > 0.009)
    edges = curl(H, back=(0, 0, 1), radius=5e-4)
    assert [edges[e]["side"] for e in EDGES] == ["back", "back", "face", "face"]
    left = edges["left"]
    expected = H[:, 0, 2].mean()         # the middle is flat: its plane is z = 0
    assert left["offset_m"] == pytest.approx(expected, rel=2e-15, abs=0)  # measured 0
    assert left["angle_deg"] == pytest.approx(np.degrees(np.arctan2(expected, 0.022)),
                                              rel=5e-15, abs=0)  # measured 6.8e-16
    # the same swatch seen with its back to −z reads the same sides
    turned = H * np.array([1.0, 1.0, -1.0])
    assert curl(turned, back=(0, 0, -1), radius=5e-4)["top"]["side"] == "back"


def test_template_jersey_dimensions():
    """The default template: ℓ = 16.8 mm (a stitch's arc of the plain-knit
    curve), course spacing w = 4.5 units, wale spacing 2π units, a unit
    r/0.75 = 0.667 mm."""
    j = Jersey(6, 6)
    P = np.stack([j.control_points(f) for f in range(j.rows)])
    s = np.linspace(0, j.nseg, 64 * j.nseg + 1)
    pts = np.stack([bspline.curve_points(p, s) for p in P])
    lengths = np.linalg.norm(np.diff(pts, axis=1), axis=-1).sum(axis=1)
    ell = loop_length(lengths, np.full(j.rows, j.cols))
    assert ell == pytest.approx(16.8e-3, rel=3e-3)        # 16.817 mm: 1.0e-3
    heads = np.stack([bspline.curve_points(P[f], j.heads(f)) for f in range(j.rows)])
    cs, ws = spacings(heads)
    assert cs == pytest.approx(4.5 * j.scale, rel=2e-15, abs=0)  # measured 2.9e-16
    assert ws == pytest.approx(2 * np.pi * j.scale, rel=2e-15, abs=0)  # measured 0


def test_a_ribs_spacings_are_those_in_its_plane():
    """Knit and purl wales' heads on either side of the fabric: its wales
    are as far apart as the width they take, measured in its plane."""
    r, c = np.indices((4, 6))
    heads = np.stack([2.0 * c, 3.0 * r, np.where(c % 2, -1.0, 1.0)], axis=-1)
    assert spacings(heads)[1] == pytest.approx(np.sqrt(8.0), rel=1e-15, abs=0)  # measured 0
    assert spacings(heads, normal=[0, 0, 1]) == (3.0, 2.0)


@pytest.mark.parametrize("repeat", [2, 4])
def test_a_ribs_heads_do_not_tilt_its_tangent_plane(repeat):
    """A 1×1 rib (KP) and a 2×2 rib (KKPP): heads on either side of the
    fabric, its local normals the fabric's, its spacings those in its plane
    (measured 0)."""
    r, c = np.indices((6, 10))
    knit = (c % repeat) < repeat // 2
    heads = np.stack([2.0 * c, 3.0 * r, np.where(knit, 1.0, -1.0)], axis=-1)
    n = surface_normals(heads)
    assert np.abs(n[2:-2, 2:-2] - [0, 0, 1]).max() < 1e-15
    assert spacings(heads, n) == pytest.approx((3.0, 2.0), rel=1e-15, abs=0)


def test_a_rolled_swatchs_spacings_are_along_its_surface():
    """Heads on a cylinder rolled along the courses (a stitch 30° of it) are
    as far apart as their chords (measured 0), where the plane of the middle
    shortens the wales by 13 % (cos 30°, the median turn of the middle's
    wales)."""
    r, c = np.indices((8, 10))
    R, turn = 7e-3, np.radians(30.0) * (c - 4.5)
    heads = np.stack([R * np.sin(turn), 3e-3 * r, R * (1 - np.cos(turn))], axis=-1)
    chord = 2 * R * np.sin(np.radians(15.0))
    assert spacings(heads, surface_normals(heads)) == pytest.approx(
        (3e-3, chord), rel=1e-14, abs=0)
    assert spacings(heads, [0, 0, 1])[1] == pytest.approx(np.cos(np.radians(30)) * chord,
                                                          rel=1e-14, abs=0)


def test_turned_is_the_rigid_motion_between_two_placements():
    """A turn and a shift of a point set are recovered to round-off (measured
    2e-16)."""
    X = np.random.default_rng(3).normal(size=(40, 3))
    R = np.linalg.qr(np.random.default_rng(4).normal(size=(3, 3)))[0]
    R *= np.sign(np.linalg.det(R))
    assert np.abs(turned(X, X @ R.T + [1.0, 2.0, -3.0]) - R).max() < 2e-15
