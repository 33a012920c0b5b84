"""Jersey geometry: interpolation of the closed-form curve, contacts, no
penetration at rest."""

import numpy as np
import pytest

from knitfem.yarn import bspline
from knitfem.contact import constraints
from knitfem.knit.pattern import DT, T0, Jersey, jersey_fabric, min_yarn_distance


def test_control_point_count_and_interpolation():
    j = Jersey(3, 5)
    P = j.control_points(1)
    assert P.shape == (8 * 5 + 3, 3)
    s = np.arange(j.nseg + 1.0)
    assert np.allclose(bspline.curve_points(P, s), j.centreline(T0 + s * DT, 1),
                       rtol=0, atol=7e-14 * j.scale)  # measured 3.5e-18


@pytest.mark.parametrize("rows,cols", [(2, 1), (4, 6)])
def test_no_penetration_at_rest(rows, cols):
    j = Jersey(rows, cols, radius=1e-3)
    fab = jersey_fabric(j)
    d, f, g = min_yarn_distance(fab.curves(fab.X), 16)
    assert f != g
    assert d >= 2 * j.radius


def test_contacts_are_closest_approach_between_neighbours():
    j = Jersey(3, 4)
    k, sa, sb = j.contacts()
    assert len(k) == 2 * 4 * 2
    Pa, Pb = j.control_points(0), j.control_points(1)
    D = bspline.curve_points(Pa, sa[:8]) - bspline.curve_points(Pb, sb[:8])
    # stationarity: the offset is normal to both curves
    # measured 1e-14
    assert np.abs(np.sum(D * bspline.curve_points(Pa, sa[:8], 1), -1)).max() < 2e-13 * j.scale**2
    # measured 9.9e-15
    assert np.abs(np.sum(D * bspline.curve_points(Pb, sb[:8], 1), -1)).max() < 1e-13 * j.scale**2
    # and a local minimum: nudging either parameter moves the points apart
    dist = np.linalg.norm(D, axis=-1)
    for da, db in ((0.05, 0), (-0.05, 0), (0, 0.05), (0, -0.05)):
        Dn = bspline.curve_points(Pa, sa[:8] + da) - bspline.curve_points(Pb, sb[:8] + db)
        assert np.all(np.linalg.norm(Dn, axis=-1) > dist)
    assert np.all(dist >= 2 * j.radius)


def test_every_constraint_row_evaluates_its_point():
    """The contacts' factors are the separation and tangents of the paired
    curve points; the holds evaluate the top course's loop heads."""
    j = Jersey(3, 2)
    fab = jersey_fabric(j, hold="top")
    contacts, holds = constraints.build(fab)
    X = fab.X.reshape(-1, 3)
    assert np.abs(contacts.values(X[contacts.cols])).max() < 1e-15 * j.scale
    assert np.abs(holds.residual(X)).max() < 1e-15
    ya, sa, yb, sb = fab.contacts
    P = [fab.yarn(f) for f in range(fab.nyarn)]
    r, t_a = contacts.factors(X[contacts.cols])[1][:, :2].transpose(1, 0, 2)
    sep = np.stack([bspline.curve_points(P[a], s) - bspline.curve_points(P[b], t)
                    for a, s, b, t in zip(ya, sa, yb, sb)])
    tan = np.stack([bspline.curve_points(P[a], s, 1) for a, s in zip(ya, sa)])
    assert np.allclose(r, sep, rtol=0, atol=7e-18)  # measured 6.5e-19
    assert np.allclose(t_a, tan, rtol=0, atol=3e-15 * np.abs(tan).max())  # measured 0
    heads = bspline.curve_points(P[2], j.heads(2))
    # measured 0
    assert np.allclose(holds.rhs[holds.kind == "fixed"], heads, rtol=0, atol=2e-17)
    assert np.all(holds.owner == 2)
