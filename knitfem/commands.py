"""The ``knitfem`` commands; each reads its options and does one job."""

import json
import os

import numpy as np
from petsc4py import PETSc

from .options import KnitError, KnitOptions
from .pattern import Jersey, LoopShape, jersey_fabric, min_yarn_distance

__all__ = ["dofs", "pattern", "run", "deform"]


def jersey_from_options(opts, rows=7, cols=7):
    """The jersey declared by -knit_rows, -knit_cols, -knit_radius."""
    r = opts.getInt("rows", rows, "courses (rows) of stitches; one yarn each", 1)
    c = opts.getInt("cols", cols, "stitches (columns) a course", 1)
    radius = opts.getReal("radius", 5e-4, "yarn radius [m]", positive=True)
    return Jersey(r, c, radius, LoopShape())


def pull_from_options(opts, jersey):
    """(stitch, force) of the pulled scene: -knit_pull_stitch c,r and
    -knit_pull_force fx,fy,fz [N]."""
    stitch = opts.getInts("pull_stitch", (jersey.cols // 2, 0),
                          "pulled scene: stitch (column, course) whose loop head "
                          "is pulled", 2, 0)
    raw = opts.getString("pull_force", "0,-0.005,0", "pulled scene: point force "
                         "fx,fy,fz [N]")
    try:
        force = [float(v) for v in raw.split(",")]
    except ValueError:
        force = []
    if len(force) != 3 or not np.all(np.isfinite(force)):
        raise KnitError(f"-knit_pull_force {raw!r}: expected three numbers "
                        "fx,fy,fz in newtons")
    return stitch, force


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


def material_from_options(opts):
    """Yarn material from -knit_rho, -knit_EA, -knit_EI, -knit_gravity, -knit_damping."""
    from .model import Material

    d = Material()
    return Material(
        rho=opts.getReal("rho", d.rho, "linear density [kg/m]", positive=True),
        EA=opts.getReal("EA", d.EA, "axial stiffness EA [N]", positive=True),
        EI=opts.getReal("EI", d.EI, "bending stiffness EI [N m^2]", nonnegative=True),
        gravity=opts.getReal("gravity", d.gravity, "gravity g along -y [m/s^2]"),
        damping=opts.getReal("damping", d.damping,
                             "mass-proportional damping c_d [1/s]", nonnegative=True))


def build_system(comm, opts, fabric, material):
    """The full, reduced or mixed model of -knit_model, from a fabric."""
    from .mixed import mixed_from_options
    from .model import FullModel
    from .reduced import ReducedModel, embedding_from_options

    kind = opts.getChoice("model", "full", ("full", "reduced", "mixed"),
                          "mechanical model")
    nq = opts.getInt("quadrature", 4, "Gauss points a yarn segment", 1)
    stage = PETSc.Log.Stage("Model set-up")
    stage.push()
    try:
        full = FullModel(comm, fabric, material, nq=nq)
        if kind == "full":
            return full
        embedding = embedding_from_options(opts, comm, fabric, full.layout)
        if kind == "mixed":
            return mixed_from_options(opts, full, embedding)
        return ReducedModel(full, embedding)
    finally:
        stage.pop()


VIEWS = {"hanging": "side", "pulled": "front", "freefall": "oblique", "catenary": "front",
         "cantilever": "front"}


def run(comm):
    """Simulate a scene with the full or reduced model (or solve its statics)."""
    from solvers.integrators import INTEGRATORS, SimulationError, StaticSolver

    from .adapt import adaptation_from_options
    from .scenes import SCENES, make_fabric
    from .simulation import Simulation

    opts = KnitOptions()
    scene = opts.getChoice("scene", "hanging", SCENES, "scene")
    jersey = jersey_from_options(opts)
    length = opts.getReal("length", 0.1, "yarn length [m] (catenary, cantilever)",
                          positive=True)
    span = opts.getReal("span", 0.08, "distance between the pins [m] (catenary)",
                        positive=True)
    nseg = opts.getInt("segments", 40, "segments of the single yarn (catenary, "
                       "cantilever)", 1)
    tilt = opts.getReal("tilt", 90.0, "start turned by this angle [deg] about the "
                        "held course (hanging: 90 horizontal, 0 hanging)")
    pull = pull_from_options(opts, jersey)
    material = material_from_options(opts)
    t_end = opts.getReal("t_end", 3.0, "simulated time [s]", positive=True)
    dt = opts.getReal("dt", 1e-2, "time step [s]", positive=True)
    method = opts.getChoice("integrator", "implicit", tuple(INTEGRATORS), "integrator")
    static = opts.getBool("static", False, "solve for the static equilibrium instead "
                          "(Newton with load stepping, -static_snes_* options)")
    load_steps = opts.getInt("load_steps", 5, "load steps of the static solve", 1)
    every = opts.getInt("output_every", 10, "steps between progress lines and "
                        "output frames", 1)
    snaps = opts.getString("snapshots", "0.4,1,2,3", "times of the PNG snapshots [s]")
    ckpt = opts.getInt("checkpoint_every", 0, "steps between HDF5 checkpoints "
                       "(0: none)", 0)
    restart = opts.getString("restart", "", "continue from this HDF5 checkpoint")
    drift = opts.getReal("drift_tol", 1e-6, "largest constraint violation [m] "
                         "before the run stops", positive=True)
    try:
        snapshots = [float(s) for s in snaps.split(",") if s]
    except ValueError:
        raise KnitError(f"-knit_snapshots {snaps!r}: expected comma-separated "
                        "times in seconds") from None
    out = output_dir(f"out/{scene}")
    try:
        fabric = make_fabric(scene, jersey, length, span, nseg, jersey.radius, tilt,
                             pull)
    except ValueError as err:
        raise KnitError(str(err)) from None
    system = build_system(comm, opts, fabric, material)
    adapt = adaptation_from_options(opts, system)
    opts.printHelp("knitfem run")
    PETSc.Sys.Print(f"knitfem run: {scene}, {system.kind} model, "
                    f"{system.M.getSize()[0]} coordinates + "
                    f"{system.C.getSize()[0]} constraints, {comm.size} rank(s)")
    if static:
        return run_static(comm, system, scene, out, load_steps, StaticSolver)
    with PETSc.Log.Stage("Solver set-up"):
        integrator = INTEGRATORS[method](system, dt)
    sim = Simulation(system, integrator, out=out, scene=scene, output_every=every,
                     snapshots=snapshots, drift_tol=drift, checkpoint_every=ckpt,
                     view=VIEWS[scene], adapt=adapt)
    if restart:
        sim.restart(restart)
    if adapt is not None:
        adapt(sim)                   # the indicator (and regions) at the start
    try:
        rec = sim.run(t_end)
    except SimulationError as err:
        PETSc.Sys.Print(f"knitfem run: error: {err} (output so far kept in {out})")
        return 3
    if adapt is not None:
        adapt.report(sim, out)
    PETSc.Sys.Print(f"done: {rec['steps']} steps in {rec['wall_time_s']:.2f} s; "
                    f"centroid {np.round(rec['centroid'], 6).tolist()}, sag "
                    f"{rec['sag']:.4g} m; summary in {out}/summary.json")


def run_static(comm, system, scene, out, load_steps, StaticSolver):
    """Static equilibrium by Newton with load stepping; writes summary.json."""
    import time

    from solvers.integrators import SimulationError

    from .simulation import Simulation

    start = time.perf_counter()
    with PETSc.Log.Stage("Static solve"):
        solver = StaticSolver(system, load_steps)
        sim = Simulation(system, solver, out=out, scene=scene, verbose=False)
        P0, pts0 = sim.geometry()
        if comm.rank == 0:
            sim.initial_lowest = pts0[..., 1].min()
        try:
            its = solver.solve(sim.x, monitor=lambda i, load, snes: PETSc.Sys.Print(
                f"load step {i}/{load_steps}  load {load:.2f}  newton "
                f"{snes.getIterationNumber()}  |F| {snes.getFunctionNorm():.3e}"))
        except SimulationError as err:
            PETSc.Sys.Print(f"knitfem run: error: {err}")
            return 3
    sim.wall_time = time.perf_counter() - start
    sim.stats["newton"] = its
    rec = sim.summary()
    if comm.rank == 0 and out:
        from . import io

        P, _ = sim.geometry()
        io.write_centrelines(os.path.join(out, f"{scene}_static.vtu"), P,
                             system.fabric.radius)
        io.draw(os.path.join(out, f"{scene}_static.png"), P, system.fabric.radius,
                title=f"{scene}, static equilibrium ({system.kind} model)")
    PETSc.Sys.Print(f"static equilibrium in {its} Newton iterations; tip "
                    f"{np.round(rec['tip'], 6).tolist()}, sag {rec['sag']:.4g} m")


def fitting_metrics(fabric, P, nq=4):
    """Quality of the stitches fitting for deformed control points P.

    max and RMS Green–Lagrange axial strain, the smallest centreline distance
    between different yarns over 2r (penetration when < 1) and the largest
    contact residual |P_f(s_a) − P_g(s_b) − d_ab| over r.
    """
    from . import constraints as cons
    from .yarn import YarnElements

    nseg = fabric.ncp - 3
    conn = (np.arange(fabric.nyarn)[:, None, None] * fabric.ncp
            + np.arange(nseg)[None, :, None] + np.arange(4)).reshape(-1, 4)
    el = YarnElements(fabric.X.reshape(-1, 3), conn, 1.0, 1.0, 0.0, nq=nq)
    e = el.strain(P.reshape(-1, 3))
    dist = min_yarn_distance(list(P), 16)[0]
    c = cons.build(fabric)
    res = np.linalg.norm(c.residual(P.reshape(-1, 3))[c.kind == "contact"], axis=1)
    return dict(max_strain=float(np.abs(e).max()),
                rms_strain=float(np.sqrt(np.mean(e**2))),
                min_distance_over_2r=float(dist / (2 * fabric.radius)),
                penetration=bool(dist < 2 * fabric.radius),
                max_contact_residual_over_r=float(res.max() / fabric.radius)
                if res.size else 0.0)


def deform(comm):
    """Move the bounding volume's control points; rebuild the yarns through Γ."""
    from . import io
    from .volume import DEFAULT_AMOUNTS, MODES, BoundingVolume

    opts = KnitOptions()
    jersey = jersey_from_options(opts, 15, 30)
    mode = opts.getChoice("mode", "flexion", MODES, "imposed deformation")
    amount = opts.getReal("amount", DEFAULT_AMOUNTS[mode], "amount: degrees "
                          "(flexion, shear, torsion) or stretch ratio (traction)")
    lod = opts.getInts("lod", (5, 5), "bounding-volume control points n1,n2", 2, 4)
    out = output_dir(f"out/deform_{mode}")
    opts.printHelp("knitfem deform")
    if comm.rank:
        return
    fabric = jersey_fabric(jersey)
    volume = BoundingVolume.around(fabric.X.reshape(-1, 3), *lod, margin=jersey.radius)
    params = volume.embed(fabric.X.reshape(-1, 3))
    try:
        moved = volume.deformed(mode, amount)
    except ValueError as err:
        raise KnitError(f"-knit_mode {mode} -knit_amount {amount:g}: {err}") from None
    cols, vals = moved.weights(*params)
    P = np.einsum("na,nai->ni", vals, moved.flat[cols]).reshape(fabric.X.shape)
    rec = dict(mode=mode, amount=amount, lod=list(lod), rows=jersey.rows,
               cols=jersey.cols, **fitting_metrics(fabric, P))
    base = os.path.join(out, f"{mode}")
    io.write_centrelines(base + ".vtu", P, jersey.radius)
    moved.save(base + "_volume.vtu")
    view = "side" if mode in ("flexion", "torsion") else "front"
    io.draw(base + ".png", P, jersey.radius, view=view,
            title=f"{mode} {amount:g}: max strain {rec['max_strain']:.3f}, "
                  f"min distance {rec['min_distance_over_2r']:.2f} x 2r")
    with open(os.path.join(out, "metrics.json"), "w") as f:
        json.dump(rec, f, indent=1)
    PETSc.Sys.Print(json.dumps(rec))
