"""What a reduced Newton iteration costs, against the yarn count and the
volume size, sampled (ECSW, ``knitfem/lod/sampling.py``) and exact.

    .venv/bin/python -m benchmarks.lod_cost [-bench_sizes 15x30,30x60,60x120,105x400]
        [-bench_lods 4x4,5x5,7x7,9x9] [-bench_t_end 0.05] [-bench_exact_max 60x120]
        [-bench_results DIR]

The hanging jersey, backward Euler dt = 1e-2 s (``benchmarks.common.case``).
Part 1: the sizes on one 5×5×2 volume; part 2: the volumes around the first
size. Each case records the time a Newton iteration (stepping wall time over
Newton iterations), the model set-up (with the training of the sampled set:
the study trains in a fresh cache, so the set-up includes it), the sampled
set's size and force errors, the unknowns and the centroid at t_end (and
its distance from the exact model's: the accuracy bought); the
training-free quadrature baseline (-knit_sampling quadrature) beside them.
Writes ``lod_cost.json`` and ``figures/lod_cost.png``.
"""

import os
import tempfile

import numpy as np

from benchmarks.common import (PETSc, KnitError, KnitOptions, case, markdown_table,
                               read_json, record, run, save_figure, sizes_option,
                               write_json)

STUDY = "lod_cost"
SAMPLINGS = ("sampled", "quadrature", "exact")


def one(comm, rows, cols, lod, sampling, t_end):
    PETSc.Sys.Print(f"{rows}x{cols}, volume {lod[0]}x{lod[1]}, {sampling} ...")
    r, _ = case(comm, dict(knit_model="reduced", knit_rows=rows, knit_cols=cols,
                           knit_lod=f"{lod[0]},{lod[1]}", knit_sampling=sampling), t_end)
    r.update(rows=rows, cols=cols, lod=list(lod), sampling=sampling,
             yarn_elements=rows * (8 * cols + 3 - 3))
    if "failed" not in r:
        r["ms_per_newton"] = 1e3 * r["wall_s"]["run"] / max(1, r["newton"])
        r["set_up_s"] = r["wall_s"]["model"]
        r["sampled"] = r["summary"].get("sampling")
    return r


def off_exact(r, cases):
    """|centroid − the exact model's| [mm] at t_end for the same jersey and
    volume ("-" without an exact run): what the sampling costs in accuracy."""
    ref = next((e for e in cases if e["sampling"] == "exact" and "summary" in e
                and (e["rows"], e["cols"], e["lod"]) == (r["rows"], r["cols"], r["lod"])),
               None)
    if ref is None or "summary" not in r:
        return "-"
    return 1e3 * float(np.linalg.norm(np.subtract(r["summary"]["centroid"],
                                                  ref["summary"]["centroid"])))


def table(cases):
    rows = []
    for r in cases:
        s = r.get("sampled") or {}
        rows.append([f"{r['rows']}x{r['cols']}", "x".join(map(str, r["lod"])),
                     r["sampling"], r["yarn_elements"],
                     f"{s['elements']}" if s else "all", r.get("unknowns", "-"),
                     r.get("ms_per_newton", r.get("failed", "-")),
                     r.get("set_up_s", "-"),
                     s.get("training_error", "-"), s.get("held_out_error", "-"),
                     off_exact(r, cases)])
    return markdown_table(["jersey", "volume", "forces", "yarn elements", "sampled",
                           "unknowns", "ms / Newton it", "set-up [s]",
                           "force error (training)", "(held out)",
                           "centroid vs exact [mm]"], rows)


def plot(rec):
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for part, ax, key, label in ((rec["sizes"], axes[0], "yarn_elements",
                                  "yarn elements (5x5x2 volume)"),
                                 (rec["volumes"], axes[1], "unknowns",
                                  f"reduced unknowns ({rec['volumes'][0]['rows']}x"
                                  f"{rec['volumes'][0]['cols']} jersey)")):
        for sampling, marker in zip(SAMPLINGS, "o^s"):
            pts = [(r[key], r["ms_per_newton"]) for r in part
                   if r["sampling"] == sampling and "ms_per_newton" in r]
            if pts:
                x, y = zip(*sorted(pts))
                ax.plot(x, y, marker=marker, label=sampling)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(label)
        ax.set_ylabel("wall time a Newton iteration [ms]")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.suptitle("reduced model, hanging jersey, backward Euler dt = 1e-2 s")
    save_figure(fig, STUDY)


def report(comm, rec):
    PETSc.Sys.Print(table(rec["sizes"]))
    PETSc.Sys.Print(table(rec["volumes"]))
    if comm.rank == 0:
        plot(rec)


def main():
    comm = PETSc.COMM_WORLD
    opts = KnitOptions("bench_")
    sizes = sizes_option(opts, "15x30,30x60,60x120,105x400")
    raw = opts.getString("lods", "4x4,5x5,7x7,9x9", "volumes n1xn2 around the first size")
    try:
        lods = [tuple(int(v) for v in s.split("x")) for s in raw.split(",") if s]
    except ValueError:
        lods = []
    if not lods or any(len(v) != 2 or min(v) < 4 for v in lods):
        raise KnitError(f"-bench_lods {raw!r}: expected n1xn2,... with n1, n2 >= 4")
    t_end = opts.getReal("t_end", 0.05, "simulated time [s]", positive=True)
    cap = opts.getString("exact_max", "60x120", "largest jersey the exact model runs")
    only_report = opts.getBool("plot", False, "only print the tables and draw the "
                               "figure of the JSON file")
    opts.printHelp(f"benchmarks.{STUDY} (and the -knit_ options of knitfem run)")
    if only_report:
        return report(comm, read_json(STUDY))
    most = np.prod([int(v) for v in cap.split("x")])
    cache = tempfile.mkdtemp(prefix="knitfem-cache-") if comm.rank == 0 else None
    os.environ["XDG_CACHE_HOME"] = comm.tompi4py().bcast(cache)
    rec = record(comm, STUDY, t_end=t_end, sizes=[], volumes=[])
    for rows, cols in sizes:
        for sampling in SAMPLINGS:
            if sampling == "exact" and rows * cols > most:
                continue
            rec["sizes"].append(one(comm, rows, cols, (5, 5), sampling, t_end))
    rows, cols = sizes[0]
    for lod in lods:
        for sampling in SAMPLINGS:
            rec["volumes"].append(one(comm, rows, cols, lod, sampling, t_end))
    for part in ("sizes", "volumes"):      # no run-by-run PETSc logs in the file
        for r in rec[part]:
            r.pop("log", None)
            r.get("summary", {}).pop("energy_history", None)
    write_json(comm, STUDY, rec)
    report(comm, rec)


if __name__ == "__main__":
    raise SystemExit(run(main, STUDY))
