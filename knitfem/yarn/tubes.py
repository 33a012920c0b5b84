"""Yarn surfaces as triangle meshes: the sampled centrelines swept by a polygon.

Sample i of a yarn, at x_i with unit tangent t_i ∝ x_{i+1} − x_{i−1}
(one-sided at an open yarn's ends), carries a ring of k vertices

    v_ij = x_i + r (cos φ_j u_i + sin φ_j w_i),   φ_j = 2π j / k,  w_i = t_i × u_i,

whose normal u_i is carried along the yarn by parallel transport,
u_i = R_i u_{i−1}, R_i the smallest rotation taking t_{i−1} to t_i (no twist
about the centreline). For u ⟂ t_{i−1} it is

    R_i u = u − (u · t_i) / (1 + t_{i−1} · t_i) (t_{i−1} + t_i).

Transport is sequential; it is vectorised by writing u_i = rot(θ_i, t_i) a_i
about a reference normal a_i made from each tangent alone (the unit axis
least aligned with t_i, projected ⟂ t_i): R_i commutes with the rotations
about the tangents, so θ_i = θ_{i−1} + ψ_i with ψ_i the angle about t_i from
a_i to R_i a_{i−1}, a cumulative sum. A closed yarn's frame comes back turned
by its holonomy Θ; the wrapped Θ ∈ (−π, π] is taken out in proportion to the
arclength (a uniform twist), so the ring closes on itself.

Consecutive rings are joined by 2k triangles, oriented outward; an open
yarn's end rings are capped by fans of k − 2 triangles (no vertex off the
surface), so every yarn is a closed surface.
"""

from typing import NamedTuple

import numpy as np

__all__ = ["TubeMesh", "tube_mesh", "yarn_colours"]

SIDES = 8


class TubeMesh(NamedTuple):
    """points (V, 3); triangles (T, 3) int32; yarn (V,) each vertex's yarn;
    normals (V, 3), the unit outward normals of the swept circle."""

    points: np.ndarray
    triangles: np.ndarray
    yarn: np.ndarray
    normals: np.ndarray


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _within(values, first):
    """Cumulative sums of ``values`` restarted at each group; ``first`` (n,)
    the index of each entry's group start."""
    total = np.cumsum(values)
    return total - total[first] + values[first]


def tube_mesh(samples, closed, radius, sides=SIDES):
    """The yarns of ``samples`` (``curves.Samples``) as one triangle mesh of
    ``sides``-gon tubes of radius ``radius`` (``TubeMesh``); ``closed``
    (nyarn,) bool: a closed yarn's last sample repeats its first and is
    dropped, its last ring joined to its first."""
    closed = np.broadcast_to(np.asarray(closed, bool), (samples.nyarn,))
    count = np.diff(samples.start) - closed          # rings of each yarn
    begin = np.concatenate([[0], np.cumsum(count)])
    yarn = np.repeat(np.arange(samples.nyarn), count)
    first = begin[yarn]
    last = begin[yarn + 1] - 1
    x = samples.points[samples.start[yarn] + np.arange(len(yarn)) - first]
    ring = np.arange(len(yarn))
    wrap = closed[yarn]
    prev = np.where(ring > first, ring - 1, np.where(wrap, last, ring))
    nxt = np.where(ring < last, ring + 1, np.where(wrap, first, ring))
    t = _unit(x[nxt] - x[prev])

    # reference normals a_i, and the angle psi_i from a_i to R_i a_{i-1}
    axis = np.eye(3)[np.argmin(np.abs(t), axis=1)]
    a = _unit(axis - np.sum(axis * t, axis=1, keepdims=True) * t)

    def turn(i, j):
        """Angle about t_j from a_j to a_i transported from t_i to t_j."""
        b = a[i] - (np.sum(a[i] * t[j], axis=1) / (1 + np.sum(t[i] * t[j], axis=1))
                    )[:, None] * (t[i] + t[j])
        return np.arctan2(np.sum(np.cross(a[j], b) * t[j], axis=1),
                          np.sum(a[j] * b, axis=1))

    psi = np.where(ring > first, turn(prev, ring), 0.0)
    theta = _within(psi, first)
    if closed.any():                 # take out each closed yarn's holonomy
        step = np.linalg.norm(x[nxt] - x[ring], axis=1)
        arc = _within(step, first) - step        # arclength from the first ring
        length = arc[last] + step[last]
        holonomy = theta[last] + turn(last, first)
        holonomy -= 2 * np.pi * np.round(holonomy / (2 * np.pi))
        theta = theta - np.where(wrap, holonomy * arc / length, 0.0)
    u = np.cos(theta)[:, None] * a + np.sin(theta)[:, None] * np.cross(t, a)
    w = np.cross(t, u)

    phi = 2 * np.pi * np.arange(sides) / sides
    normals = (np.cos(phi)[None, :, None] * u[:, None]
               + np.sin(phi)[None, :, None] * w[:, None])          # (rings, k, 3)
    points = x[:, None] + radius * normals

    # sides: rings g0 -> g1, vertex g k + j
    join = (ring < last) | wrap
    g0, g1 = ring[join], nxt[join]
    j0 = np.arange(sides)
    j1 = (j0 + 1) % sides
    a0, a1 = g0[:, None] * sides + j0, g0[:, None] * sides + j1
    b0, b1 = g1[:, None] * sides + j0, g1[:, None] * sides + j1
    faces = [np.stack([a0, a1, b1], -1), np.stack([a0, b1, b0], -1)]
    # caps of the open yarns: fans from vertex 0, facing -t at the start
    ends = np.flatnonzero(~closed)
    j = np.arange(1, sides - 1)
    for g, sign in ((begin[ends], -1), (begin[ends + 1] - 1, 1)):
        v0 = np.broadcast_to(g[:, None] * sides, (len(g), sides - 2))
        vj, vk = g[:, None] * sides + j, g[:, None] * sides + j + 1
        faces.append(np.stack([v0, vj, vk] if sign > 0 else [v0, vk, vj], -1))
    triangles = np.concatenate([f.reshape(-1, 3) for f in faces]).astype(np.int32)
    return TubeMesh(points.reshape(-1, 3), triangles, np.repeat(yarn, sides),
                    normals.reshape(-1, 3))


def yarn_colours(nyarn):
    """(nyarn, 3) uint8 RGB, one colour a yarn: hues H a golden ratio of the
    circle apart (neighbouring yarns differ), saturation S = 0.6 and value
    V = 0.9; channel n (5, 3, 1 for red, green, blue) is
    V − V S clip(min(k, 4 − k), 0, 1), k = (n + 6 H) mod 6."""
    hue = np.arange(nyarn) * 0.618033988749895 % 1.0
    k = (np.array([5, 3, 1]) + 6 * hue[:, None]) % 6
    rgb = 0.9 * (1 - 0.6 * np.clip(np.minimum(k, 4 - k), 0, 1))
    return np.round(255 * rgb).astype(np.uint8)
