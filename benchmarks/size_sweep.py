"""Cost of the full model as the jersey grows, to more than 10⁶ coordinates.

    .venv/bin/python -m benchmarks.size_sweep \\
        -bench_sizes 10x10,20x40,40x80,80x160,105x400 -bench_profile 25
    mpirun -n 2 .venv/bin/python -m benchmarks.size_sweep \\
        -bench_sizes 10x10,20x40,40x80,80x160,105x400 -bench_profile 25
    .venv/bin/python -m benchmarks.size_sweep -bench_plot
    # strong scaling, per-rank event times: results/size_sweep_np<P>_strong.json
    .venv/bin/python -m benchmarks.size_sweep -bench_sizes 20x40,40x80,80x160 \\
        -bench_tag strong
    mpirun -n 2 .venv/bin/python -m benchmarks.size_sweep \\
        -bench_sizes 20x40,40x80,80x160 -bench_tag strong

For each size, the hanging scene of ``knitfem run`` (full model, top course
held, backward Euler) is set up and advanced -bench_steps steps: set-up
wall time split into fabric (pattern, contacts), model (elements, M, C) and
integrator (tangent at rest, saddle-point matrix, SNES), the first step's
factorisation (symbolic and numeric: times and counts, so one analysis a
run shows as one MatCholFctrSym), the time of a step, Newton iterations,
peak memory and, on more than one rank, the time of each event on each
rank (``log``, ``rank_times``). -bench_profile N adds the N costliest
functions by cProfile (rank 0). A size that fails (a factorisation out of
memory, say) is recorded with its reason, and the larger ones skipped, as
is a size predicted to take longer than -bench_budget seconds. Writes
results/size_sweep_np<P>.json; -bench_plot draws results/figures/size_sweep.png
(time against coordinates, log-log) from the np1 and np2 files.
"""

import cProfile
import os
import pstats
import sys

from .common import (RESULTS, KnitOptions, PETSc, case, markdown_table, read_json,
                     record, run, save_figure, sizes_option, write_json)

STUDY = "size_sweep"


def top_functions(profile, n):
    """The n functions of largest cumulative time: [name, calls, tottime, cumtime]."""
    stats = pstats.Stats(profile)
    rows = sorted(stats.stats.items(), key=lambda kv: -kv[1][3])[:n]
    return [[f"{os.path.relpath(f) if f.startswith('/') else f}:{line}({name})",
             nc, round(tt, 3), round(ct, 3)]
            for (f, line, name), (_, nc, tt, ct, _) in rows]


def summarise(r):
    """The figures of one size from its case record."""
    if "failed" in r and "wall_s" not in r:
        return
    setup = r["log"].get("Model set-up", {})
    step = r["log"].get("Time stepping", {})

    def t(events, name):
        return events.get(name, {}).get("time", 0.0)

    def n(events, name):
        return events.get(name, {}).get("count", 0)

    r["seconds"] = dict(
        fabric=r["wall_s"]["fabric"], model=r["wall_s"]["model"],
        assembly=t(setup, "knitAssembly"), integrator=r["wall_s"]["integrator"],
        factor_symbolic=t(step, "MatLUFactorSym") + t(step, "MatCholFctrSym"),
        factor_numeric=t(step, "MatLUFactorNum") + t(step, "MatCholFctrNum"),
        tangent=t(step, "knitTangent"), forces=t(step, "knitForces"))
    r["factorisations"] = dict(
        symbolic=n(step, "MatLUFactorSym") + n(step, "MatCholFctrSym"),
        numeric=n(step, "MatLUFactorNum") + n(step, "MatCholFctrNum"),
        solves=n(step, "MatSolve"))
    if "run" in r["wall_s"]:
        r["seconds"]["step"] = r["wall_s"]["run"] / max(r["steps"], 1)
        r["seconds"]["newton_iteration"] = r["wall_s"]["run"] / max(r["newton"], 1)


def skipped(last, stitches, budget):
    """Why the next size is skipped (or None): the last one failed, or its
    time scaled by (stitches ratio)^1.5 (a sparse factorisation of a 2-D
    graph) exceeds the budget."""
    if "failed" in last:
        return f"{last['rows']}x{last['cols']} failed"
    ratio = stitches / (last["rows"] * last["cols"])
    predicted = last["wall_s"]["total"] * ratio**1.5
    if predicted > budget:
        return (f"predicted {predicted:.0f} s from {last['rows']}x{last['cols']} "
                f"> -bench_budget {budget:g} s")
    return None


def plot(recs, name=STUDY):
    """Set-up, factorisation and step time against coordinates (rank 0)."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5), layout="constrained")
    parts = (("set-up", lambda x: x["fabric"] + x["model"] + x["integrator"]),
             ("symbolic factorisations", lambda x: x["factor_symbolic"]),
             ("numeric factorisations", lambda x: x["factor_numeric"]),
             ("one step", lambda x: x.get("step", float("nan"))))
    for rec, style in zip(recs, ("o-", "s--", "d:")):
        runs = [r for r in rec["runs"] if "seconds" in r]
        for color, (label, value) in enumerate(parts):
            ax.loglog([r["coordinates"] for r in runs],
                      [value(r["seconds"]) for r in runs], style, color=f"C{color}",
                      label=f"{label}, np {rec['ranks']}")
    ax.set_xlabel("coordinates (3 x control points)")
    ax.set_ylabel("wall time [s]")
    ax.set_title("full model, hanging jersey, backward Euler")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    save_figure(fig, name)


RANK_EVENTS = ("SNESSolve", "knitForces", "knitTangent", "knitAssembly",
               "MatCholFctrSym", "MatCholFctrNum", "MatSolve", "MatMult", "KSPSolve")


def rank_table(log, ranks):
    """Markdown table: each event of the time-stepping stage, its count and
    its time on each rank."""
    events = log.get("Time stepping", {})
    rows = [[name, events[name]["count"], *events[name]["rank_times"]]
            for name in RANK_EVENTS if "rank_times" in events.get(name, {})]
    return markdown_table(["event", "count", *(f"rank {i}" for i in range(ranks))],
                          rows)


def report(comm, tag=""):
    """Tables of every size_sweep_np*.json; the figure on rank 0."""
    suffix = f"_{tag}" if tag else ""
    names = sorted(f[:-5] for f in os.listdir(RESULTS)
                   if f.startswith(STUDY + "_np") and f.endswith(suffix + ".json")
                   and (tag or f[len(STUDY) + 3:-5].isdigit()))
    recs = [read_json(name) for name in names]
    for rec in recs:
        rows = []
        for r in rec["runs"]:
            s = r.get("seconds", {})
            nf = r.get("factorisations", {})
            rows.append([f"{r['rows']}x{r['cols']}", r.get("coordinates", "-"),
                         r.get("constraints", "-"), *(s.get(k, "-") for k in (
                             "fabric", "model", "integrator", "factor_symbolic",
                             "factor_numeric", "step", "newton_iteration")),
                         r.get("newton", "-"),
                         f"{nf.get('symbolic', '-')}/{nf.get('numeric', '-')}"
                         f"/{nf.get('solves', '-')}",
                         r.get("memory", {}).get("peak_rss_mib_max", "-"),
                         r.get("failed", r.get("skipped", ""))])
        header = ["size", "coordinates", "constraints", "fabric [s]", "model [s]",
                  "integrator [s]", "symbolic factor. [s]", "numeric factor. [s]",
                  "step [s]", "Newton it. [s]", "Newton its",
                  "symbolic/numeric factor./solves", "peak RSS/rank [MiB]", "note"]
        PETSc.Sys.Print(f"np = {rec['ranks']}, {rec['steps']} step(s)\n"
                        + markdown_table(header, rows))
        for r in rec["runs"]:
            if rec["ranks"] > 1 and "log" in r:
                PETSc.Sys.Print(f"{r['rows']}x{r['cols']}, time stepping, seconds "
                                "by rank\n" + rank_table(r["log"], rec["ranks"]))
        for r in rec["runs"]:
            if "profile" in r:
                PETSc.Sys.Print(f"cProfile, {r['rows']}x{r['cols']}, rank 0\n"
                                + markdown_table(["function", "calls", "tottime [s]",
                                                  "cumtime [s]"], r["profile"]))
    if comm.rank == 0 and recs:
        plot(recs, STUDY + suffix)


def main():
    comm = PETSc.COMM_WORLD
    opts = KnitOptions("bench_")
    sizes = sizes_option(opts, "10x10,20x40,40x80,80x160,105x400")
    steps = opts.getInt("steps", 1, "backward Euler steps a size", 1)
    budget = opts.getReal("budget", 900.0, "skip a size predicted to take longer "
                          "than this [s]", positive=True)
    nprof = opts.getInt("profile", 0, "report the N costliest functions (cProfile)", 0)
    only_report = opts.getBool("plot", False, "only print the tables and draw the "
                               "figure of the JSON files")
    tag = opts.getString("tag", "", "suffix of the result files "
                         "(size_sweep_np<P>_<tag>.json)")
    opts.printHelp(f"benchmarks.{STUDY} (and the -knit_ options of knitfem run)")
    if only_report:
        return report(comm, tag)
    if PETSc.Options().hasName("help"):
        return
    runs, last = [], None
    for rows, cols in sizes:
        skip = last and skipped(last, rows * cols, budget)
        if skip:
            runs.append(dict(rows=rows, cols=cols, skipped=skip))
            continue
        PETSc.Sys.Print(f"{rows}x{cols} ...")
        profile = cProfile.Profile() if nprof and comm.rank == 0 else None
        if profile:
            profile.enable()
        r, _ = case(comm, dict(knit_rows=rows, knit_cols=cols, knit_model="full"),
                    steps=steps)
        if profile:
            profile.disable()
            r["profile"] = top_functions(profile, nprof)
        r.update(rows=rows, cols=cols)
        summarise(r)
        runs.append(r)
        last = r
    write_json(comm, f"{STUDY}_np{comm.size}" + (f"_{tag}" if tag else ""),
               record(comm, STUDY, steps=steps, runs=runs))
    report(comm, tag)


if __name__ == "__main__":
    sys.exit(run(main, STUDY))
