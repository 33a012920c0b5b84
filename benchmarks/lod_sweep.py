"""Level of detail: error of the reduced model against the full one, and cost.

    .venv/bin/python -m benchmarks.lod_sweep -bench_sizes 7x7 -bench_t_end 3
    .venv/bin/python -m benchmarks.lod_sweep -bench_sizes 15x30 -bench_tag 15x30
    .venv/bin/python -m benchmarks.lod_sweep -bench_sizes 7x7 -knit_hold corner -knit_tilt 0 -bench_tag corner
    .venv/bin/python -m benchmarks.lod_sweep -bench_plot   # tables, figure

The hanging scene of ``knitfem run`` with the full model (the reference)
and the reduced model at n1 x n2 bounding-volume control points, from 4x4 up
to one patch a stitch (n1 = cols + 3, n2 = rows + 3), in -bench_levels
steps (or the list -bench_lods 4x4,6x6,...). At t_end: the RMS and largest
distance of the yarn control points (ε = Γα) from the full model's, and the
drop difference; with the unknowns and the wall time. The reduced models
are sampled (ECSW) unless -knit_sampling exact (or quadrature) says
otherwise; -bench_tag keeps the runs apart. Writes
results/lod_sweep[_TAG].json and results/figures/lod_sweep[_TAG].png (error
and time against unknowns).
"""

import os
import sys

import numpy as np

from .common import (RESULTS, KnitError, KnitOptions, PETSc, case, drop, forced,
                     log_since, log_snapshot, markdown_table, memory, read_json,
                     record, rms_distance, run, save_figure, sizes_option, wall,
                     write_json)

STUDY = "lod_sweep"


def default_lods(rows, cols, levels):
    """4x4, then n_i = 3 + ceil(stitches_i k / K), k = 1 … K: up to a patch a
    stitch."""
    K = min(rows, cols, levels)
    lods = [(4, 4)] + [(3 + -(-cols * k // K), 3 + -(-rows * k // K))
                       for k in range(1, K + 1)]
    return sorted(set(lods), key=lods.index)


def lods_option(opts):
    """A function (rows, cols) → volume sizes, from -bench_lods or -bench_levels."""
    levels = opts.getInt("levels", 7, "volume sizes from 4x4 to a patch a stitch", 1)
    raw = opts.getString("lods", "", "explicit volume sizes N1xN2,... (overrides "
                         "-bench_levels)")
    if not raw:
        return lambda rows, cols: default_lods(rows, cols, levels)
    try:
        lods = [tuple(int(v) for v in s.split("x")) for s in raw.split(",")]
    except ValueError:
        lods = []
    if not lods or any(len(n) != 2 or min(n) < 4 for n in lods):
        raise KnitError(f"-bench_lods {raw!r}: expected N1xN2,... with N >= 4")
    return lambda rows, cols: lods


def plot(rec):
    """Error and wall time against unknowns, one line a size (rank 0)."""
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4.2), layout="constrained")
    for size in rec["sizes"]:
        ok = [r for r in size["reduced"] if "error" in r]
        n = [r["unknowns"] for r in ok]
        label = f"{size['rows']}x{size['cols']}"
        ax1.loglog(n, [r["error"]["rms_over_radius"] for r in ok], "o-",
                   label=f"{label} RMS")
        ax1.loglog(n, [r["error"]["max_over_radius"] for r in ok], "s--",
                   label=f"{label} max")
        for r in ok:
            ax1.annotate(f"{r['lod'][0]}x{r['lod'][1]}", (r["unknowns"],
                         r["error"]["rms_over_radius"]), fontsize=6)
        ax2.loglog(n, [r["wall_s"]["total"] for r in ok], "o-",
                   label=f"{label} reduced")
        full = size["full"]
        if "wall_s" in full and "total" in full["wall_s"]:
            ax2.loglog([full["unknowns"]], [full["wall_s"]["total"]], "k*",
                       markersize=10, label=f"{label} full")
    ax1.set_xlabel("unknowns (coordinates + constraints)")
    ax1.set_ylabel("control-point distance to the full model / yarn radius")
    ax2.set_xlabel("unknowns (coordinates + constraints)")
    ax2.set_ylabel("wall time [s]")
    for ax in (ax1, ax2):
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"hanging jersey, reduced vs full at t = {rec['t_end']:g} s",
                 fontsize=10)
    save_figure(fig, rec["name"])


def error(P, Pref, drop, drop_ref, radius):
    d = np.linalg.norm(P - Pref, axis=-1)
    return dict(rms_over_radius=rms_distance(P, Pref) / radius,
                max_over_radius=float(d.max()) / radius,
                drop_relative_difference=(drop - drop_ref) / drop_ref)


def sweep(comm, rows, cols, t_end, lods):
    """The full reference and the reduced models of one size."""
    base = dict(knit_rows=rows, knit_cols=cols)
    PETSc.Sys.Print(f"{rows}x{cols} full ...")
    full, Pref = case(comm, dict(base, knit_model="full"), t_end, points=True)
    out = dict(rows=rows, cols=cols, full=full, reduced=[])
    for n1, n2 in lods(rows, cols):
        PETSc.Sys.Print(f"{rows}x{cols} reduced {n1}x{n2} ...")
        r, P = case(comm, dict(base, knit_model="reduced", knit_lod=f"{n1},{n2}"),
                    t_end, points=True)
        r["lod"] = [n1, n2]
        if "failed" not in r and "failed" not in full:
            r["error"] = comm.tompi4py().bcast(error(
                P, Pref, drop(r["summary"]), drop(full["summary"]), full["radius"])
                if comm.rank == 0 else None)
        out["reduced"].append(r)
    return out


def report(comm, rec):
    """Print the table; draw the figure on rank 0."""
    rows = []
    for s in rec["sizes"]:
        for r in [s["full"]] + s["reduced"]:
            e = r.get("error", {})
            rows.append([f"{s['rows']}x{s['cols']}",
                         "x".join(map(str, r["lod"])) if "lod" in r else "full",
                         r.get("unknowns", "-"), r.get("newton", "-"), wall(r),
                         1e3 * drop(r["summary"]) if "summary" in r else "-",
                         e.get("rms_over_radius", "-"), e.get("max_over_radius", "-"),
                         drop(e, "drop_relative_difference")])
    PETSc.Sys.Print(markdown_table(
        ["size", "model", "unknowns", "Newton its", "wall [s]", "drop [mm]",
         "RMS dist / r", "max dist / r", "rel. drop diff."], rows))
    if comm.rank == 0:
        plot(rec)


# -- mixed and adaptive rows: the pulled swatch ---------------------------------
def pulled_case(comm, options, t_end):
    """The pulled scene with the -knit_ ``options`` forced, as ``knitfem run``
    builds it (with the indicator and -knit_adapt for the mixed model).
    Returns the record, the control points at t_end (rank 0) and the
    adaptation (or None). Collective."""
    import time

    from knitfem.lod.adapt import adaptation_from_options
    from knitfem.cli.commands import (build_system, jersey_from_options,
                                      material_from_options)
    from knitfem.cli.scenes import Pulled
    from knitfem.run.simulation import Simulation
    from solvers.integrators import INTEGRATORS, SimulationError

    before, rec, P, adapt = log_snapshot(), dict(forced=dict(options)), None, None
    with forced(options):
        opts = KnitOptions()
        try:
            comm.barrier()
            start = time.perf_counter()
            jersey = jersey_from_options(opts)
            fabric = Pulled.from_options(opts, jersey).fabric(jersey)
            system = build_system(comm, opts, fabric, material_from_options(opts))
            dt = opts.getReal("dt", 1e-2, "time step [s]", positive=True)
            method = opts.getChoice("integrator", "implicit", tuple(INTEGRATORS),
                                    "integrator")
            with PETSc.Log.Stage("Solver set-up"):
                integrator = INTEGRATORS[method](system, dt)
                adapt = adaptation_from_options(opts, system)
            n, k = system.M.getSize()[0], system.C.getSize()[0]
            rec.update(coordinates=n, constraints=k, unknowns=n + k,
                       radius=fabric.radius,
                       pull=[int(fabric.loads[0][0]), float(fabric.loads[1][0])])
            verbose = KnitOptions("bench_").getBool("verbose", False, "progress")
            sim = Simulation(system, integrator, out=None, verbose=verbose,
                             adapt=adapt)
            if adapt is not None:
                adapt(sim)
            summary = sim.run(t_end)
            comm.barrier()
            rec["wall_s"] = dict(run=sim.wall_time, total=time.perf_counter() - start)
            rec.update(steps=summary["steps"], newton=summary["newton_iterations"],
                       ksp=summary["ksp_iterations"], summary=summary)
            if adapt is not None:
                rec.update(adapt.record())
                rec["unknowns"] = rec["adapt"]["unknowns_max"]
            P = np.asarray(sim.geometry()[0]) if comm.rank == 0 else None
        except (SimulationError, PETSc.Error, KnitError) as err:
            rec["failed"] = str(err).strip().splitlines()[-1]
            PETSc.Sys.Print(f"  failed: {rec['failed']}")
    rec.update(memory=memory(comm), log=log_since(before, comm))
    return rec, P, adapt


def reference(comm, path, t_end):
    """The full model's record and points from a ``knitfem run`` directory."""
    import json
    import os

    import h5py

    with open(os.path.join(path, "summary.json")) as f:
        summary = json.load(f)
    with h5py.File(os.path.join(path, "checkpoint.h5"), "r") as f:
        t, x = float(f.attrs["t"]), f["x"][...]
    if abs(t - t_end) > 1e-9 or summary.get("model") != "full":
        raise KnitError(f"-bench_reference {path}: holds a {summary.get('model')} "
                        f"model at t = {t:g} s, not the full model at {t_end:g} s")
    rec = dict(reference=path, unknowns=summary["unknowns"], steps=summary["steps"],
               newton=summary["newton_iterations"], summary=summary,
               wall_s=dict(run=summary["wall_time_s"], total=summary["wall_time_s"]))
    return rec, x


def near_pull(fabric, pull_yarn, pull_s, radius_stitches):
    """Control points within ``radius_stitches`` stitch widths of the pulled
    loop head at rest: a boolean (N,) mask."""
    from knitfem.knit.pattern import SEGMENTS_PER_STITCH

    cols, b = fabric.point_rows([pull_yarn], [pull_s])
    X = fabric.X
    head = b[0] @ X[cols[0]]
    width = np.abs(X[SEGMENTS_PER_STITCH + 1, 0] - X[1, 0])
    return np.linalg.norm(X - head, axis=-1) <= radius_stitches * width


def split_error(P, Pref, near, radius):
    d2 = np.sum((P - Pref) ** 2, axis=-1)
    return dict(near_rms_over_radius=float(np.sqrt(d2[near].mean())) / radius,
                elsewhere_rms_over_radius=float(np.sqrt(d2[~near].mean())) / radius,
                rms_over_radius=rms_distance(P, Pref) / radius,
                max_over_radius=float(np.sqrt(d2.max())) / radius)


PULLED_MODELS = {"reduced": dict(knit_model="reduced"),
                 "adaptive": dict(knit_model="mixed", knit_adapt="")}


def pulled_study(comm, rows, cols, t_end, ref_dir, radius_near, name,
                 models=tuple(PULLED_MODELS)):
    """Full (or its reference ``ref_dir``), reduced, and adaptive mixed on the
    pulled swatch; errors near the pull and elsewhere."""
    from knitfem.lod.adapt import draw_history
    from knitfem.knit.pattern import Jersey, jersey_fabric

    base = dict(knit_rows=rows, knit_cols=cols)
    PETSc.Sys.Print(f"pulled {rows}x{cols} full ...")
    if ref_dir:
        full, x = reference(comm, ref_dir, t_end)
        Pref = x.reshape(-1, 3)
    else:
        full, Pref, _ = pulled_case(comm, dict(base, knit_model="full"), t_end)
    out = dict(rows=rows, cols=cols, full=full, models=[])
    fabric = jersey_fabric(Jersey(rows, cols))
    for label in models:
        extra = PULLED_MODELS[label]
        PETSc.Sys.Print(f"pulled {rows}x{cols} {label} ...")
        r, P, adapt = pulled_case(comm, dict(base, **extra), t_end)
        r["label"] = label
        if "failed" not in r and "failed" not in full and comm.rank == 0:
            near = near_pull(fabric, *r["pull"], radius_near)
            r["error"] = split_error(P, Pref, near, r["radius"])
            r["near_points"] = int(near.sum())
            r["unknowns_over_full"] = r["unknowns"] / full["unknowns"]
            r["wall_full_over_this"] = full["wall_s"]["run"] / r["wall_s"]["run"]
        r = comm.tompi4py().bcast(r if comm.rank == 0 else None)
        if adapt is not None and comm.rank == 0:
            draw_history(os.path.join(RESULTS, "figures", f"{name}_indicator.png"),
                         adapt.full.fabric, adapt.weights, adapt.history,
                         adapt.refine, adapt.coarsen)
        out["models"].append(r)
    return out


def pulled_report(comm, rec):
    """Table of the pulled rows; bars of error and wall time (rank 0)."""
    rows = []
    for s in rec["sizes"]:
        f = s["full"]
        rows.append([f"{s['rows']}x{s['cols']}", "full", f["unknowns"], f["newton"],
                     f["wall_s"]["run"], "-", "-", "-", "-"])
        for r in s["models"]:
            e = r.get("error", {})
            rows.append([f"{s['rows']}x{s['cols']}", r["label"], r.get("unknowns", "-"),
                         r.get("newton", "-"), wall(r),
                         e.get("near_rms_over_radius", "-"),
                         e.get("elsewhere_rms_over_radius", "-"),
                         r.get("unknowns_over_full", "-"),
                         r.get("wall_full_over_this", "-")])
    PETSc.Sys.Print(markdown_table(
        ["size", "model", "unknowns (max)", "Newton its", "wall [s]",
         "RMS dist / r near pull", "RMS dist / r elsewhere", "unknowns / full",
         "full wall / this"], rows))
    if comm.rank:
        return
    import matplotlib.pyplot as plt

    s = rec["sizes"][0]
    ok = [r for r in s["models"] if "error" in r]
    labels = [r["label"] for r in ok]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(9, 3.6), layout="constrained")
    x = np.arange(len(ok))
    ax1.bar(x - 0.2, [r["error"]["near_rms_over_radius"] for r in ok], 0.4,
            label="near the pull")
    ax1.bar(x + 0.2, [r["error"]["elsewhere_rms_over_radius"] for r in ok], 0.4,
            label="elsewhere")
    ax1.set_xticks(x, labels)
    ax1.set_ylabel("RMS distance to the full model / yarn radius")
    ax1.legend(fontsize=7)
    ax2.bar(["full"] + labels, [s["full"]["wall_s"]["run"]]
            + [r["wall_s"]["run"] for r in ok])
    ax2.set_ylabel("wall time of the run [s]")
    fig.suptitle(f"pulled {s['rows']}x{s['cols']} swatch, t = {rec['t_end']:g} s",
                 fontsize=10)
    save_figure(fig, rec["name"])


def main():
    comm = PETSc.COMM_WORLD
    opts = KnitOptions("bench_")
    scene = opts.getChoice("scene", "hanging", ("hanging", "pulled"),
                           "hanging: reduced models against the full one; pulled: "
                           "the reduced and adaptive mixed models")
    sizes = sizes_option(opts, "7x7")
    t_end = opts.getReal("t_end", 3.0, "simulated time [s]", positive=True)
    tag = opts.getString("tag", "", "suffix of the result and figure names")
    only_report = opts.getBool("plot", False, "only print the table and draw the "
                               "figure of the JSON file")
    lods = lods_option(opts)
    ref_dir = opts.getString("reference", "", "pulled: knitfem run output directory "
                             "of the full model (checkpoint.h5 at t_end)")
    radius_near = opts.getReal("near", 2.0, "pulled: near the pull means within "
                               "this many stitch widths of the pulled loop head",
                               positive=True)
    raw = opts.getString("models", ",".join(PULLED_MODELS), "pulled: models to "
                         "run against the full one")
    models = [m for m in raw.split(",") if m]
    if not models or any(m not in PULLED_MODELS for m in models):
        raise KnitError(f"-bench_models {raw!r}: expected a list of "
                        f"{', '.join(PULLED_MODELS)}")
    opts.printHelp(f"benchmarks.{STUDY} (and the -knit_ options of knitfem run)")
    name = STUDY + (f"_{tag}" if tag else "")
    show = pulled_report if scene == "pulled" else report
    if only_report:
        return show(comm, read_json(name))
    if scene == "pulled":
        if not PETSc.Options().hasName("help"):
            rec = record(comm, STUDY, name=name, t_end=t_end, scene=scene, sizes=[
                pulled_study(comm, r, c, t_end, ref_dir, radius_near, name, models)
                for r, c in sizes])
            write_json(comm, name, rec)
            show(comm, rec)
        return
    if PETSc.Options().hasName("help"):
        return
    rec = record(comm, STUDY, name=name, t_end=t_end,
                 sizes=[sweep(comm, r, c, t_end, lods) for r, c in sizes])
    write_json(comm, name, rec)
    report(comm, rec)


if __name__ == "__main__":
    sys.exit(run(main, STUDY))
