"""Full vs reduced model on the hanging jersey: cost and result.

    .venv/bin/python -m benchmarks.full_vs_reduced -bench_sizes 7x7,15x30 -bench_t_end 3
    .venv/bin/python -m benchmarks.full_vs_reduced -bench_plot   # tables, figure

The hanging scene of ``knitfem run`` (backward Euler, dt = 1e-2, start
horizontal) for each size, with the full model and the reduced model of
-bench_lod (5,5), sampled (ECSW, the default) and exact. Per model: wall time, the time of a step split by PETSc
events, the time of a Newton iteration by part (forces, tangent, Γᵀ K Γ,
factorisation and solves, the rest), Newton iterations, unknowns, drop of the lowest point,
centroid and lowest point; per size: the relative drop difference and the
centroid distance of the reduced result from the full one. Writes
results/full_vs_reduced[_TAG].json and results/figures/full_vs_reduced.png
(time a Newton iteration, stacked by part, before and after).

"Before" is the numpy-kernel code of main before the compiled kernels (its
runs are kept in the JSON under ``before``, carried from file to file).

Things to try: -bench_t_end 0.2 for a quick check; -knit_EI 2e-7.
"""

import sys

import numpy as np

from .common import (KnitOptions, PETSc, case, drop, markdown_table, read_json, record, run,
                     save_figure, sizes_option, split_table, step_split, wall,
                     write_json)

STUDY = "full_vs_reduced"
MODELS = ("full", "reduced", "reduced exact")     # reduced: sampled (ECSW)
PARTS = {"forces": ("forces", "residual other"), "tangent": ("tangent",),
         "Γᵀ K Γ": ("PtAP",), "factor/solve": ("PC set-up (factorisation)",
                                               "triangular solves"),
         "other": ("Jacobian other", "Krylov, line search", "driver")}


def iteration_split(run):
    """Seconds a Newton iteration by part (``PARTS``): the step split times
    the steps over the Newton iterations. "forces" holds every residual
    evaluation of the iteration (line search included)."""
    per = run["per_step_s"]
    scale = run["steps"] / max(run["newton"], 1)
    return {part: scale * sum(per[k] for k in keys) for part, keys in PARTS.items()}


def before_runs(name):
    """The "before" runs of the existing result file: its own ``before``, or,
    for a file written before the compiled kernels, its runs."""
    try:
        old = read_json(name)
    except OSError:
        return []
    if "before" in old:
        return old["before"]
    return [dict(rows=r["rows"], cols=r["cols"], model=r["model"],
                 newton=r["newton"], steps=r["steps"], wall_s=r["wall_s"],
                 per_step_s=r["per_step_s"], summary=dict(drop=drop(r["summary"])))
            for r in old["runs"] if "per_step_s" in r]


def compare(full, reduced):
    """Relative drop difference and centroid distance, reduced vs full."""
    if "failed" in full or "failed" in reduced:
        return None
    sf, sr = drop(full["summary"]), drop(reduced["summary"])
    dc = np.subtract(reduced["summary"]["centroid"], full["summary"]["centroid"])
    return dict(drop_relative_difference=(sr - sf) / sf,
                centroid_distance=float(np.linalg.norm(dc)))


def plot(rec):
    """Time a Newton iteration stacked by part, before and after, one panel
    a size (rank 0)."""
    import matplotlib.pyplot as plt

    runs = [r for r in rec["runs"] if "per_step_s" in r]
    sizes = sorted({(r["rows"], r["cols"]) for r in runs})
    fig, axes = plt.subplots(1, len(sizes), figsize=(2.2 + 3.2 * len(sizes), 4.2),
                             squeeze=False, layout="constrained")
    for ax, (rows, cols) in zip(axes[0], sizes):
        bars = [(f"{r['model']}\n{when}", iteration_split(r))
                for r0 in runs if (r0["rows"], r0["cols"]) == (rows, cols)
                for when, r in (("before", match(rec.get("before", []), r0)), ("after", r0))
                if r is not None]
        bottom = np.zeros(len(bars))
        for part in PARTS:
            h = np.array([1e3 * split[part] for _, split in bars])
            ax.bar([label for label, _ in bars], h, bottom=bottom, label=part)
            bottom += h
        ax.set_ylabel("wall time a Newton iteration [ms]")
        ax.tick_params(axis="x", labelsize=7)
        ax.set_title(f"{rows}x{cols}")
    axes[0, -1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1))
    first = runs[0]["summary"]                   # "dt" in results before dt_next
    fig.suptitle(f"hanging jersey, backward Euler dt = {first.get('dt_next', first.get('dt')):g}, "
                 f"t_end = {rec['t_end']:g} s, {rec['ranks']} rank(s)", fontsize=10)
    save_figure(fig, rec["name"])


def match(runs, r):
    """The run of ``runs`` with r's size and model, or None."""
    return next((b for b in runs if (b["rows"], b["cols"], b["model"])
                 == (r["rows"], r["cols"], r["model"])), None)


def report(comm, rec):
    """Print the tables; draw the figure on rank 0."""
    rows = []
    for r in rec["runs"]:
        s = r.get("summary")
        rows.append([f"{r['rows']}x{r['cols']}", r["model"], r.get("unknowns", "-"),
                     r.get("newton", "-"), wall(r),
                     1e3 * r["wall_s"]["run"] / r["steps"] if s else "-",
                     1e3 * drop(s) if s else "-",
                     str(np.round(s["lowest_point"], 5).tolist()) if s else "-",
                     str(np.round(s["centroid"], 5).tolist()) if s else "-"])
    PETSc.Sys.Print(markdown_table(
        ["size", "model", "unknowns", "Newton its", "wall [s]", "ms/step", "drop [mm]",
         "lowest point [m]", "centroid [m]"], rows))
    ok = [r for r in rec["runs"] if "per_step_s" in r]
    PETSc.Sys.Print(split_table([f"{r['rows']}x{r['cols']} {r['model']}" for r in ok],
                                [r["per_step_s"] for r in ok]))
    lines = []
    for r in ok:
        for when, one in (("before", match(rec.get("before", []), r)), ("after", r)):
            if one is not None:
                split = iteration_split(one)
                lines.append([f"{r['rows']}x{r['cols']}", r["model"], when,
                              one["newton"], one["wall_s"]["run"],
                              *(1e3 * split[p] for p in PARTS),
                              1e3 * sum(split.values())])
    PETSc.Sys.Print(markdown_table(
        ["size", "model", "code", "Newton its", "run [s]",
         *(f"{p} [ms/it]" for p in PARTS), "total [ms/it]"], lines))
    PETSc.Sys.Print(markdown_table(
        ["size", "model", "relative drop difference", "centroid distance [mm]"],
        [[f"{d['rows']}x{d['cols']}", d.get("model", "reduced"),
          drop(d, "drop_relative_difference"), 1e3 * d["centroid_distance"]]
         for d in rec["differences"]]))
    if comm.rank == 0 and ok:
        plot(rec)


def main():
    comm = PETSc.COMM_WORLD
    opts = KnitOptions("bench_")
    sizes = sizes_option(opts, "7x7,15x30")
    t_end = opts.getReal("t_end", 3.0, "simulated time [s]", positive=True)
    lod = opts.getInts("lod", (5, 5), "reduced model: volume control points n1,n2",
                       2, 4)
    tag = opts.getString("tag", "", "suffix of the result and figure names")
    only_report = opts.getBool("plot", False, "only print the tables and draw the "
                               "figure of the JSON file")
    opts.printHelp(f"benchmarks.{STUDY} (and the -knit_ options of knitfem run)")
    name = STUDY + (f"_{tag}" if tag else "")
    if only_report:
        return report(comm, read_json(name))
    if PETSc.Options().hasName("help"):
        return
    runs, diffs = [], []
    for rows, cols in sizes:
        pair = {}
        for model in MODELS:
            PETSc.Sys.Print(f"{rows}x{cols} {model} ...")
            kind, _, sampling = model.partition(" ")
            options = dict(knit_rows=rows, knit_cols=cols, knit_model=kind)
            if kind == "reduced":
                options.update(knit_lod=f"{lod[0]},{lod[1]}",
                               knit_sampling=sampling or "sampled")
            r, _ = case(comm, options, t_end)
            r.update(rows=rows, cols=cols, model=model)
            if "failed" not in r:
                r["per_step_s"] = step_split(r)
            pair[model] = r
            runs.append(r)
        for model in MODELS[1:]:
            d = compare(pair["full"], pair[model])
            if d:
                diffs.append(dict(rows=rows, cols=cols, model=model, **d))
    rec = record(comm, STUDY, name=name, t_end=t_end, lod=list(lod), runs=runs,
                 differences=diffs, before=before_runs(name))
    write_json(comm, name, rec)
    report(comm, rec)


if __name__ == "__main__":
    sys.exit(run(main, STUDY))
