"""The ``knitfem`` commands; each reads its options and does one job."""

import json
import os

import numpy as np
from petsc4py import PETSc

from .options import KnitError, KnitOptions
from .pattern import Jersey, LoopShape, jersey_fabric, min_yarn_distance

__all__ = ["dofs", "pattern"]


def jersey_from_options(opts, rows=7, cols=7):
    """The jersey declared by -knit_rows, -knit_cols, -knit_radius."""
    r = opts.getInt("rows", rows, "courses (rows) of stitches; one yarn each", 1)
    c = opts.getInt("cols", cols, "stitches (columns) a course", 1)
    radius = opts.getReal("radius", 5e-4, "yarn radius [m]", positive=True)
    return Jersey(r, c, radius, LoopShape())


def output_dir(default):
    """The -o DIR option, created on rank 0."""
    path = PETSc.Options().getString("o", default)
    if PETSc.COMM_WORLD.rank == 0:
        try:
            os.makedirs(path, exist_ok=True)
        except OSError as err:
            raise KnitError(f"-o {path}: cannot create the output directory "
                            f"({err.strerror})") from None
    return path


def dofs(comm):
    """Print the unknowns table (Figure 9) counted from the assembled objects."""
    from .model import FullModel, Material
    from .reduced import embedding_from_options

    opts = KnitOptions()
    jersey = jersey_from_options(opts, 15, 30)
    fmt = opts.getChoice("format", "table", ("table", "json"), "output format")
    fabric = jersey_fabric(jersey)
    emb = embedding_from_options(opts, comm, fabric)
    opts.printHelp("knitfem dofs")
    full = FullModel(comm, fabric, Material())
    ncp_yarn = full.layout.ncp_per_yarn
    dof = full.M.getSize()[0]
    scalar_con = full.C.getSize()[0]
    reduced_dofs = emb.Gamma.getSize()[1]
    rec = dict(rows=jersey.rows, cols=jersey.cols, control_points_per_yarn=ncp_yarn,
               dofs_per_yarn=3 * ncp_yarn, control_points=full.m.getSize()[0],
               dofs=dof, vector_constraints=full.c.getSize()[0],
               scalar_constraints=scalar_con, unknowns=dof + scalar_con,
               paper_scalar_constraints=3 * 2 * jersey.cols * jersey.rows,
               reduced_control_points=emb.Gamma_scalar.getSize()[1],
               reduced_dofs=reduced_dofs,
               ratio=(dof + scalar_con) / reduced_dofs)
    if fmt == "json":
        PETSc.Sys.Print(json.dumps(rec))
        return
    rows = [("Control points per yarn", rec["control_points_per_yarn"], ""),
            ("Degrees of freedom per yarn", rec["dofs_per_yarn"], ""),
            ("Control points total", rec["control_points"],
             rec["reduced_control_points"]),
            ("Degrees of freedom total", rec["dofs"], rec["reduced_dofs"]),
            ("Vector constraints total", rec["vector_constraints"], ""),
            ("Scalar constraints total", rec["scalar_constraints"], ""),
            ("Scalar unknowns total", rec["unknowns"], rec["reduced_dofs"])]
    lines = [f"{jersey.rows} rows x {jersey.cols} columns jersey, bounding volume "
             f"{emb.volume.n1}x{emb.volume.n2}x2",
             f"{'':30s}{'knitwear (initial)':>20s}{'bounding volume':>18s}"]
    lines += [f"{name:30s}{a:>20}{b:>18}" for name, a, b in rows]
    lines.append(f"{'Ratio of unknowns':30s}{rec['ratio']:>20.1f}")
    lines.append(f"(the paper counts 2 nc contacts for every course, "
                 f"{rec['paper_scalar_constraints']} scalar constraints; an open "
                 f"jersey has (r-1)·2·nc interlocks)")
    PETSc.Sys.Print("\n".join(lines))
    full.destroy()


def pattern(comm):
    """Write a jersey's centrelines (VTU) and a PNG picture."""
    from . import io

    opts = KnitOptions()
    jersey = jersey_from_options(opts)
    out = output_dir("out/pattern")
    opts.printHelp("knitfem pattern")
    if comm.rank:
        return
    fabric = jersey_fabric(jersey)
    dist, f, g = min_yarn_distance(list(fabric.X))
    base = os.path.join(out, f"jersey_{jersey.rows}x{jersey.cols}")
    io.write_centrelines(base + ".vtu", fabric.X, jersey.radius)
    io.draw(base + ".png", fabric.X, jersey.radius,
            title=f"jersey {jersey.rows}x{jersey.cols}")
    PETSc.Sys.Print(f"wrote {base}.vtu and {base}.png; {fabric.nyarn} yarns of "
                    f"{fabric.ncp} control points, min distance between yarns "
                    f"{dist / (2 * jersey.radius):.3f} x 2r")
