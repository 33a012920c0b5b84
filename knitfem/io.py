"""Output: yarn centrelines for ParaView (meshio) and PNG pictures (matplotlib).

Centrelines are the splines sampled ``SAMPLES`` times a segment, written as
"line" cells with point data ``radius`` (for ParaView's Tube filter, "Vary
radius: By Scalar"), ``yarn`` and ``course`` (the course a point knits, 0
the first knitted course); yarns have their own lengths (``curves.Curves``);
time series go to XDMF + HDF5, one file a
frame, and, for renderers, the yarns as tube meshes (PLY, OBJ or OFF) one
file a frame. Every file is written under a temporary name and renamed into place.
"""

import contextlib
import html
import os
import socket
from io import BytesIO

import h5py
import numpy as np


__all__ = ["centrelines", "write_centrelines", "atomic_write", "CentrelineSeries",
           "BodySeries", "TubeFrames", "TUBE_FORMATS", "tube_surfaces",
           "draw", "draw_panels", "animate", "VIEWS"]

def _pyplot():
    """matplotlib's pyplot on the Agg backend, imported when a picture is
    first drawn (a third of a second that runs without pictures save)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


SAMPLES = 6
SEGMENTS = 20000            # pieces of tube in a picture, about (``_draw_on``)
FIXED = ("radius", "yarn", "course")        # point data of every frame


def centrelines(P, samples=SAMPLES):
    """Sampled centrelines (``curves.Samples``) of the yarns P (``Curves``)."""
    return P.samples(samples)


def _mesh_arrays(P, radius, point_data=None):
    pts = centrelines(P)
    m = len(pts.points)
    data = {"radius": np.full(m, float(radius)), "yarn": pts.yarn.astype(float),
            "course": pts.course.astype(float)}
    for name, values in (point_data or {}).items():
        data[name] = np.asarray(values).reshape(m, -1).squeeze()
    return pts.points, [("line", pts.segments())], data


def write_centrelines(path, P, radius, point_data=None):
    """One geometry file (.vtu, .xdmf, … as meshio infers from the name)."""
    pts, cells, data = _mesh_arrays(P, radius, point_data)
    import meshio

    meshio.write(path, meshio.Mesh(pts, cells, point_data=data))


def _body_arrays(bodies, size):
    """The surfaces of ``bodies`` as one triangle mesh: (points, cells,
    point data ``body``, each point's body index); a plane is drawn as a
    square of half-side ``size``."""
    pts, tris, which = [], [], []
    for k, body in enumerate(bodies):
        p, t = body.surface(size)
        tris.append(t + sum(len(q) for q in pts))
        pts.append(p)
        which.append(np.full(len(p), k, dtype=float))
    return (np.concatenate(pts), [("triangle", np.concatenate(tris))],
            {"body": np.concatenate(which)})


def write_bodies(path, bodies, size):
    """The surfaces of ``bodies`` (``colliders``) as one triangle mesh with
    point data ``body`` (its index), for ParaView beside the yarns; a plane
    is drawn as a square of half-side ``size``."""
    import meshio

    pts, cells, data = _body_arrays(bodies, size)
    mesh = meshio.Mesh(pts, cells, point_data=data)
    atomic_write(path, lambda tmp: meshio.write(tmp, mesh, file_format="vtu"))


TUBE_FORMATS = ("ply", "obj", "off")


def tube_surfaces(P, closed, radius, file_format="ply"):
    """The yarns P (``Curves``) as a meshio triangle mesh of tubes of radius
    ``radius`` around the centreline samples of the time series (``closed``
    the fabric's closed yarns; ``yarn.tubes``). PLY carries the point data
    ``yarn`` (int32) and ``red``, ``green``, ``blue`` (uint8, one colour a
    yarn: Blender's vertex colours); OBJ the normals of the swept circles
    (smooth shading); OFF the geometry only."""
    import meshio

    from knitfem.yarn.tubes import tube_mesh as sweep, yarn_colours

    m = sweep(centrelines(P), closed, radius)
    data = {}
    if file_format == "ply":
        rgb = yarn_colours(P.nyarn)[m.yarn]
        data = dict(yarn=m.yarn.astype(np.int32), red=rgb[:, 0], green=rgb[:, 1],
                    blue=rgb[:, 2])
    elif file_format == "obj":
        data = {"obj:vn": m.normals}
    return meshio.Mesh(m.points, [("triangle", m.triangles)], point_data=data)


class TubeFrames:
    """The yarns' tube meshes, one file a frame, ``<dir>/<step>.<format>``
    (``tube_surfaces``; call on rank 0). Frames an earlier run left are removed,
    but for those up to step ``keep`` (a restart into the same directory)."""

    def __init__(self, dir, file_format, closed, radius, keep=None):
        self.dir, self.format = dir, file_format
        self.closed, self.radius = closed, radius
        os.makedirs(dir, exist_ok=True)
        self.remove(dir, keep)

    @staticmethod
    def remove(dir, keep=None):
        """Remove the frames in ``dir`` after step ``keep`` (None: all) and
        temporaries (a run without tube meshes: those of an earlier run)."""
        for name in os.listdir(dir) if os.path.isdir(dir) else ():
            stem = os.path.splitext(name)[0]
            if name.startswith(".") or (stem.isdigit() and (keep is None
                                                           or int(stem) > keep)):
                os.remove(os.path.join(dir, name))

    def write(self, step, P):
        """Frame ``step``: the yarns P (``Curves``)."""
        import meshio

        mesh = tube_surfaces(P, self.closed, self.radius, self.format)
        atomic_write(os.path.join(self.dir, f"{step:08d}.{self.format}"),
                     lambda tmp: meshio.write(tmp, mesh, file_format=self.format))


def atomic_write(path, write):
    """Write ``path`` through ``write(tmp)`` on a unique temporary name in the
    same directory, then rename: readers see the old file or the new one,
    never a part. The temporary keeps the extension (matplotlib reads it)."""
    head, tail = os.path.split(path)
    stem, ext = os.path.splitext(tail)
    tmp = os.path.join(head, f".{stem}.{socket.gethostname()}.{os.getpid()}.tmp{ext}")
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise


def write_hdf5(path, fill, **options):
    """An HDF5 file made in memory by ``fill(f)`` and written to ``path`` by
    plain file I/O: a full disk is one OSError, and HDF5 never holds a file
    whose writes failed (it would report them again from its destructors,
    and crash at exit)."""
    image = BytesIO()
    with h5py.File(image, "w", **options) as f:
        fill(f)
    with open(path, "wb") as out:
        out.write(image.getbuffer())


class CentrelineSeries:
    """XDMF time series of moving yarn centrelines, one HDF5 file a frame
    (call on rank 0).

        <stem>.xdmf              the index: a temporal collection of grids
        <stem>/mesh.h5           topology, radius, yarn, course (constant)
        <stem>/<step>.h5         geometry (and point data) of one output step

    Each frame is written to a temporary and renamed, and the index is
    rewritten the same way, so a run stopped at any instant (``kill -9``, a
    full disk) leaves a readable series of whole frames. Every grid carries
    its own geometry (ParaView's Xdmf3 reader) and the same points as the
    vector field ``position`` (meshio's ``TimeSeriesReader`` reads geometry
    once, point data per step).

    ``keep`` continues the series already in the directory with its frames
    up to that step (a restart into the same directory); otherwise earlier
    frames are removed. ``note`` is recorded in the index as an XDMF
    ``Information`` (e.g. the checkpoint a series continues from).
    """

    topology = ("Polyline", 2)      # XDMF topology type, points a cell
    constant = FIXED                # point data written once, in mesh.h5

    def __init__(self, path, P0, radius, keep=None, note=""):
        self.path, self.radius, self.note = path, radius, note
        stem = os.path.splitext(os.path.basename(path))[0]
        self.dir = os.path.join(os.path.dirname(path) or ".", stem)
        self.rel = stem
        pts, cells, data = self._arrays(P0)
        self.npts, self.ncells = len(pts), len(cells[0][1])
        self.steps, self._grids = {}, {}        # the grids: XDMF of each frame
        os.makedirs(self.dir, exist_ok=True)
        if keep is not None:
            self.steps = {s: v for s, v in self._existing().items() if s <= keep}
        for name in os.listdir(self.dir):
            step = self._step_of(name)
            if name.startswith(".") or (step is not None and step not in self.steps):
                os.remove(os.path.join(self.dir, name))

        def mesh(f):
            f["topology"] = cells[0][1]
            for key in self.constant:
                f[key] = data[key]

        atomic_write(os.path.join(self.dir, "mesh.h5"),
                     lambda tmp: write_hdf5(tmp, mesh))
        self._write_xdmf()

    def _arrays(self, P, point_data=None):
        """(points, cells, point data) of a frame's geometry P."""
        return _mesh_arrays(P, self.radius, point_data)

    @staticmethod
    def _step_of(name):
        stem, ext = os.path.splitext(name)
        return int(stem) if ext == ".h5" and stem.isdigit() else None

    def _existing(self):
        """{step: (t, {point-data name: shape})} of the whole frames on disk."""
        found = {}
        for name in os.listdir(self.dir):
            step = self._step_of(name)
            if step is None:
                continue
            try:
                with h5py.File(os.path.join(self.dir, name), "r") as f:
                    found[step] = (float(f.attrs["t"]), {
                        k: f[k].shape for k in f if k != "geometry"})
            except (OSError, KeyError):
                continue
        return found

    def write(self, step, t, P, point_data=None):
        """Frame ``step`` at time t: the yarns P (``Curves``; a body
        series: its bodies)."""
        pts, _, data = self._arrays(P, point_data)
        extra = {k: v for k, v in data.items() if k not in self.constant}
        shapes = {k: np.shape(v) for k, v in extra.items()}

        def frame(f):
            f["geometry"] = pts
            for name, values in extra.items():
                f[name] = values
            f.attrs["t"], f.attrs["step"] = float(t), int(step)

        atomic_write(os.path.join(self.dir, f"{step:08d}.h5"),
                     lambda tmp: write_hdf5(tmp, frame))
        self.steps[int(step)] = (float(t), shapes)
        self._write_xdmf()

    def _item(self, file, dataset, shape):
        dims = " ".join(map(str, shape))
        return (f'<DataItem Dimensions="{dims}" Format="HDF" NumberType="Float" '
                f'Precision="8">{self.rel}/{file}:/{dataset}</DataItem>')

    def _attribute(self, name, file, shape, dataset=None):
        kind = "Vector" if len(shape) == 2 and shape[1] == 3 else "Scalar"
        return (f'<Attribute Name="{name}" AttributeType="{kind}" Center="Node">'
                f'{self._item(file, dataset or name, shape)}</Attribute>')

    def _write_xdmf(self):
        """The index of every frame (each frame's grid made once)."""
        grids = []
        for step in sorted(self.steps):
            key = (step, self.steps[step][0])
            if key not in self._grids:
                self._grids[key] = self._grid(step)
            grids.append(self._grids[key])
        self._write_index(grids)

    def _grid(self, step):
        one, three = (self.npts,), (self.npts, 3)
        t, shapes = self.steps[step]
        frame = f"{step:08d}.h5"
        kind, per = self.topology
        return (f'<Grid Name="step{step}" GridType="Uniform"><Time Value="{t!r}"/>'
                f'<Topology TopologyType="{kind}" NodesPerElement="{per}" '
                f'NumberOfElements="{self.ncells}"><DataItem Dimensions='
                f'"{self.ncells} {per}" Format="HDF" NumberType="Int" Precision="8">'
                f'{self.rel}/mesh.h5:/topology</DataItem></Topology>'
                f'<Geometry GeometryType="XYZ">'
                f'{self._item(frame, "geometry", three)}</Geometry>'
                + self._attribute("position", frame, three, "geometry")
                + "".join(self._attribute(n, "mesh.h5", one) for n in self.constant)
                + "".join(self._attribute(n, frame, s) for n, s in shapes.items())
                + '</Grid>')

    def _write_index(self, grids):
        note = (f'<Information Name="note" Value="{html.escape(self.note)}"/>\n'
                if self.note else "")

        def index(tmp):
            with open(tmp, "w") as f:
                f.write('<?xml version="1.0"?>\n<Xdmf Version="3.0"><Domain>\n'
                        + note + f'<Grid Name="{self.rel}" GridType="Collection" '
                        'CollectionType="Temporal">\n' + "\n".join(grids)
                        + "\n</Grid></Domain></Xdmf>\n")

        atomic_write(self.path, index)



class BodySeries(CentrelineSeries):
    """The bodies' surfaces as an XDMF time series beside the yarns' (rank
    0): a frame is the tuple of bodies as they are then, ``size`` the half
    side a plane is drawn with; point data ``body`` and ``position`` (see
    ``CentrelineSeries``, whose restart and atomic writing it shares)."""

    topology = ("Triangle", 3)
    constant = ("body",)

    def __init__(self, path, bodies, size, keep=None, note=""):
        self.size = size
        super().__init__(path, bodies, 0.0, keep, note)

    def _arrays(self, bodies, point_data=None):
        return _body_arrays(bodies, self.size)

def _camera(azimuth, elevation):
    """Rows: the screen's right, up and towards-the-viewer axes in world
    coordinates, for a camera turned by ``azimuth`` about y then tilted by
    ``elevation`` (degrees) from the front view (looking along −z)."""
    a, e = np.radians(azimuth), np.radians(elevation)
    Ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(e), -np.sin(e)], [0, np.sin(e), np.cos(e)]])
    return Rx @ Ry


VIEWS = {"front": _camera(0, 0), "side": _camera(90, 0),
         "oblique": _camera(-35, 20), "three_quarter": _camera(-40, 25)}


def _projected_box(P_or_extent, view, radius):
    """(lo, hi) on screen of a fabric P or of a world box (lo, hi), padded."""
    if isinstance(P_or_extent, tuple):
        lo, hi = P_or_extent
        pts = np.array(np.meshgrid(*zip(lo, hi), indexing="ij")).reshape(3, -1).T
    else:
        pts = np.asarray(P_or_extent).reshape(-1, 3)
    box = pts @ VIEWS[view].T
    return box.min(0) - 2 * radius, box.max(0) + 2 * radius


def _scale_bar(ax, lo, hi):
    """A bar of a round length (1, 2 or 5 × 10^k m) near a fifth of the width."""
    width = hi[0] - lo[0]
    k = np.floor(np.log10(width / 5))
    length = min((m * 10**k for m in (1, 2, 5)), key=lambda b: abs(b - width / 5))
    x0, y0 = lo[0] + 0.05 * width, lo[1] + 0.05 * (hi[1] - lo[1])
    ax.plot([x0, x0 + length], [y0, y0], color="k", lw=2)
    ax.text(x0 + length / 2, y0, f"{length * 1e3:g} mm", ha="center", va="bottom",
            fontsize=8)


def _draw_bodies(ax, bodies, cam, size):
    """The surfaces of ``bodies`` as grey triangles, back to front and shaded
    by how squarely they face the viewer, behind the yarns (zorder 0)."""
    from matplotlib.collections import PolyCollection

    for body in bodies:
        p, t = body.surface(size)
        tri = (p @ cam.T)[t]                                   # (m, 3, 3)
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        facing = np.abs(n[:, 2]) / np.maximum(np.linalg.norm(n, axis=1), 1e-300)
        order = np.argsort(tri[:, :, 2].mean(axis=1))
        grey = (0.45 + 0.4 * facing[order])[:, None] * np.ones(3)
        ax.add_collection(PolyCollection(tri[order][:, :, :2], facecolors=grey,
                                         edgecolors="none", zorder=0))


def _draw_on(ax, P, radius, view, extent, bodies=()):
    """Yarns P as shaded tubes on ``ax``, back to front (painter's algorithm),
    over the ``bodies`` they rest on.

    ``extent`` (lo, hi) is a world box kept in view (default: P's own)."""
    cam = VIEWS[view]
    if bodies:
        flat = np.asarray(P).reshape(-1, 3)
        _draw_bodies(ax, bodies, cam, float(np.ptp(flat, axis=0).max()))
    # at most ~SEGMENTS pieces: up to 8 straight segments a B-spline segment,
    # and on a large knit, whose loops are a few pixels wide, polylines of
    # several B-spline segments each
    nseg = len(P.points) - 3 * P.nyarn
    samples = int(np.clip(SEGMENTS // max(1, nseg), 1, 8))
    chunk = max(1, -(-nseg // SEGMENTS))
    sampled = centrelines(P, samples=samples)
    pts, m = sampled.points @ cam.T, np.diff(sampled.start)
    pieces = -(-(m - 1) // chunk)
    yarn = np.repeat(np.arange(P.nyarn), pieces)
    piece = np.arange(pieces.sum()) - np.repeat(np.cumsum(pieces) - pieces, pieces)
    ends = np.minimum(piece[:, None] * chunk + np.arange(chunk + 1), m[yarn, None] - 1)
    seg = pts[sampled.start[yarn, None] + ends]
    depth = seg[:, :, 2].mean(axis=1)
    order = np.argsort(depth)
    lo, hi = _projected_box(_world_box([P], bodies) if extent is None
                            else tuple(extent), view, radius)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    shade = 0.55 + 0.45 * (depth - depth.min()) / (np.ptp(depth) + 1e-300)
    from matplotlib.collections import LineCollection

    colours = _pyplot().cm.tab10(yarn % 10)[:, :3] * shade[:, None]
    for outline, c in ((1.15, np.zeros_like(colours)), (1.0, colours)):
        tubes = LineCollection(seg[order][:, :, :2], colors=c[order], capstyle="round",
                               zorder=1)
        tubes.diameter = 2 * radius * outline       # in data units: _fit_widths
        ax.add_collection(tubes)
    if view == "front":
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
    elif view == "side":
        ax.set_xlabel("z [m]")
        ax.set_ylabel("y [m]")
    else:
        ax.set_axis_off()
        _scale_bar(ax, lo, hi)


def _fit_widths(fig):
    """Give every tube its diameter on screen, in points, once the layout
    (tight_layout, equal aspect) has fixed the data-to-pixel scale."""
    for ax in fig.axes:
        ax.apply_aspect()
        (x0, _), (x1, _) = ax.transData.transform([(0, 0), (1, 0)])
        points_per_unit = (x1 - x0) * 72 / fig.dpi
        for tubes in ax.collections:
            if hasattr(tubes, "diameter"):
                tubes.set_linewidth(max(0.3, tubes.diameter * points_per_unit))


def _figsize(box, width, most=12.0):
    """(width, height) in inches for a screen box (lo, hi)."""
    (x0, y0), (x1, y1) = box[0][:2], box[1][:2]
    return width, max(2.0, min(most, width * (y1 - y0) / (x1 - x0)))


def _save(fig, path):
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    try:
        atomic_write(path, fig.savefig)
    finally:
        _pyplot().close(fig)


def draw(path, P, radius, title="", view="front", extent=None, bodies=()):
    """A PNG of the fabric P (``Curves``) seen from ``view`` (see VIEWS), its
    limits fitted to P (or to the world box ``extent``)."""
    box = _projected_box(_world_box([P], bodies) if extent is None else tuple(extent),
                         view, radius)
    fig, ax = _pyplot().subplots(figsize=_figsize(box, 8.0), dpi=110)
    _draw_on(ax, P, radius, view, extent, bodies)
    ax.set_title(title)
    fig.tight_layout()
    _fit_widths(fig)
    _save(fig, path)


def draw_panels(path, frames, radius, titles, view="oblique", extent=None, bodies=None):
    """One PNG with the fabrics ``frames`` side by side, in one common view
    and scale (e.g. the snapshots of a run, as the paper's Figures 10–13);
    ``bodies`` the bodies of each frame, posed as they were then."""
    bodies, every = _per_frame(bodies, frames)
    if extent is None:
        extent = _world_box(frames, every)
    w, h = _figsize(_projected_box(extent, view, radius), 3.2, most=6.0)
    fig, axes = _pyplot().subplots(1, len(frames), figsize=(w * len(frames), h + 0.4),
                             dpi=110, squeeze=False)
    for ax, P, title, posed in zip(axes[0], frames, titles, bodies):
        _draw_on(ax, P, radius, view, extent, posed)
        ax.set_title(title)
    fig.tight_layout()
    _fit_widths(fig)
    _save(fig, path)


def _per_frame(bodies, frames):
    """(the bodies of each frame, all of them in one list); none when
    ``bodies`` is None."""
    if bodies is None:
        return [()] * len(frames), []
    if len(bodies) != len(frames):
        raise ValueError(f"{len(bodies)} frames of bodies for {len(frames)} of yarns")
    return bodies, [b for posed in bodies for b in posed]


def _world_box(frames, bodies=()):
    """(lo, hi) around every fabric in ``frames`` and the bounded bodies."""
    flat = np.concatenate([np.asarray(P).reshape(-1, 3) for P in frames]
                          + [b.surface()[0] for b in bodies if b.bounded])
    return flat.min(0), flat.max(0)


def animate(path, times, frames, radius, title="", view="three_quarter", fps=10,
            bodies=None):
    """A GIF (matplotlib.animation, Pillow) of the fabrics ``frames`` at
    ``times``, in one view and scale, 800 pixels wide (loops visible);
    ``bodies`` the bodies of each frame, posed as they were then."""
    from matplotlib.animation import FuncAnimation, PillowWriter

    bodies, every = _per_frame(bodies, frames)
    extent = _world_box(frames, every)
    fig, ax = _pyplot().subplots(figsize=_figsize(_projected_box(extent, view, radius),
                                            10.0, most=12.0), dpi=80)

    def show(k):
        ax.clear()
        _draw_on(ax, frames[k], radius, view, extent, bodies[k])
        ax.set_title(f"{title}, t = {times[k]:.2f} s")
        _fit_widths(fig)
        return []

    anim = FuncAnimation(fig, show, frames=len(frames), blit=False)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    anim.save(path, writer=PillowWriter(fps=fps))
    _pyplot().close(fig)
