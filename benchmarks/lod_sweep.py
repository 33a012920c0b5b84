"""Level of detail: error of the reduced model against the full one, and cost.

    .venv/bin/python -m benchmarks.lod_sweep -bench_sizes 7x7 -bench_t_end 3
    .venv/bin/python -m benchmarks.lod_sweep -bench_sizes 15x30 -bench_tag 15x30
    .venv/bin/python -m benchmarks.lod_sweep -bench_plot   # tables, figure

The hanging scene of ``knitfem run`` with the full model (the reference)
and the reduced model at n1 x n2 bounding-volume control points, from 4x4 up
to one patch a stitch (n1 = cols + 3, n2 = rows + 3), in -bench_levels
steps (or the list -bench_lods 4x4,6x6,...). At t_end: the RMS and largest
distance of the yarn control points (ε = Γα) from the full model's, and the
sag difference; with the unknowns and the wall time. Writes
results/lod_sweep[_TAG].json and results/figures/lod_sweep[_TAG].png (error
and time against unknowns).
"""

import sys

import numpy as np

from .common import (KnitError, KnitOptions, PETSc, case, markdown_table, read_json,
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


def error(P, Pref, sag, sag_ref, radius):
    d = np.linalg.norm(P - Pref, axis=-1)
    return dict(rms_over_radius=rms_distance(P, Pref) / radius,
                max_over_radius=float(d.max()) / radius,
                sag_relative_difference=(sag - sag_ref) / sag_ref)


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
                P, Pref, r["summary"]["sag"], full["summary"]["sag"], full["radius"])
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
                         1e3 * r["summary"]["sag"] if "summary" in r else "-",
                         e.get("rms_over_radius", "-"), e.get("max_over_radius", "-"),
                         e.get("sag_relative_difference", "-")])
    PETSc.Sys.Print(markdown_table(
        ["size", "model", "unknowns", "Newton its", "wall [s]", "sag [mm]",
         "RMS dist / r", "max dist / r", "rel. sag diff."], rows))
    if comm.rank == 0:
        plot(rec)


def main():
    comm = PETSc.COMM_WORLD
    opts = KnitOptions("bench_")
    sizes = sizes_option(opts, "7x7")
    t_end = opts.getReal("t_end", 3.0, "simulated time [s]", positive=True)
    tag = opts.getString("tag", "", "suffix of the result and figure names")
    only_report = opts.getBool("plot", False, "only print the table and draw the "
                               "figure of the JSON file")
    lods = lods_option(opts)
    opts.printHelp(f"benchmarks.{STUDY} (and the -knit_ options of knitfem run)")
    name = STUDY + (f"_{tag}" if tag else "")
    if only_report:
        return report(comm, read_json(name))
    if PETSc.Options().hasName("help"):
        return
    rec = record(comm, STUDY, name=name, t_end=t_end,
                 sizes=[sweep(comm, r, c, t_end, lods) for r, c in sizes])
    write_json(comm, name, rec)
    report(comm, rec)


if __name__ == "__main__":
    sys.exit(run(main, STUDY))
