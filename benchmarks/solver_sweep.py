"""Linear solvers for the saddle point of the implicit step, by options only.

    .venv/bin/python -m benchmarks.solver_sweep -bench_sizes 15x30 -bench_steps 5
    .venv/bin/python -m benchmarks.solver_sweep -bench_np 2 -bench_tag np2 ...
    .venv/bin/python -m benchmarks.solver_sweep -bench_plot   # tables, figure

The Newton step of backward Euler solves [A Cᵀ; C 0] (A = h²K + M), by
default with MUMPS LDLᵀ. Each configuration is an options file
``benchmarks/solver_configs/NAME.rc`` of ``-full_`` options (the implicit
SNES/KSP prefix; fieldsplit fields "u" and "l"), usable as
``knitfem run -options_file benchmarks/solver_configs/NAME.rc``. The sweep
runs every configuration (or -bench_configs a,b) in a fresh process,
``[mpirun -n NP] python -m benchmarks.solver_sweep -options_file NAME.rc
-bench_config NAME`` plus this command line, so no option leaks from one to
the next, on the hanging full model for -bench_steps steps: time a step
split by events, Newton and KSP iterations, success or the reason of the
failure, and the largest and RMS distance of the final control points from
those of -bench_reference (mumps_ldlt, the default). Writes
results/solver_sweep[_TAG].json and results/figures/solver_sweep[_TAG].png.
Run the sweep itself without mpirun.
"""

import json
import os
import subprocess
import sys

import numpy as np

from .common import (RESULTS, KnitError, KnitOptions, PETSc, case, markdown_table,
                     read_json, record, rms_distance, run, save_figure, sizes_option,
                     split_table, stacked_bars, step_split, write_json)

STUDY = "solver_sweep"
CONFIGS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "solver_configs")


def configurations():
    """{name: (description, options)} of the shipped .rc files."""
    out = {}
    for fname in sorted(os.listdir(CONFIGS)):
        if fname.endswith(".rc"):
            with open(os.path.join(CONFIGS, fname)) as f:
                lines = [s.strip() for s in f if s.strip()]
            text = " ".join(s.lstrip("# ") for s in lines if s.startswith("#"))
            options = " ".join(s for s in lines if not s.startswith("#"))
            out[fname[:-3]] = (text, options)
    return out


def tmp_path(name):
    return os.path.join(RESULTS, f"{STUDY}_{name}.tmp")


def child(comm, name, rows, cols, steps):
    """Run one configuration (this process's options); write its .tmp record."""
    r, P = case(comm, dict(knit_rows=rows, knit_cols=cols, knit_model="full"),
                steps=steps, points=True)
    r["config"] = name
    if "failed" not in r:
        r["per_step_s"] = step_split(r)
    if comm.rank == 0:
        r["points"] = None if P is None else P.tolist()
        os.makedirs(RESULTS, exist_ok=True)
        with open(tmp_path(name), "w") as f:
            json.dump(r, f)


def spawn(name, nproc, timeout):
    """The record of configuration ``name`` from a fresh process."""
    rc = os.path.join(CONFIGS, name + ".rc")
    cmd = ([] if nproc == 1 else ["mpirun", "-n", str(nproc)]) + [
        sys.executable, "-m", f"benchmarks.{STUDY}", "-options_file", rc,
        *sys.argv[1:], "-bench_config", name]
    PETSc.Sys.Print(f"{name} ...")
    if os.path.exists(tmp_path(name)):
        os.remove(tmp_path(name))
    try:
        # os.environ is the environment from before MPI started: the OMPI_/PMIX_
        # variables of this (singleton) MPI process would break a child mpirun
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout,
                           cwd=os.path.dirname(os.path.dirname(CONFIGS)),
                           env=dict(os.environ))
    except subprocess.TimeoutExpired:
        return dict(config=name, failed=f"timeout after {timeout:g} s")
    if not os.path.exists(tmp_path(name)):
        tail = [s for s in (p.stderr + p.stdout).splitlines() if s.strip()]
        return dict(config=name, failed=f"exit {p.returncode}: "
                    + (tail[-1] if tail else "no output"))
    with open(tmp_path(name)) as f:
        r = json.load(f)
    os.remove(tmp_path(name))
    return r


def compare(runs, reference):
    """Distance of each final state from the reference configuration's (or,
    when that one failed, the first that did not)."""
    points = {r["config"]: r.pop("points", None) for r in runs}
    ok = [c for c, P in points.items() if P is not None]
    ref = reference if points.get(reference) is not None else next(iter(ok), None)
    for r in runs:
        P = points[r["config"]]
        if ref is None or P is None:
            continue
        d = np.linalg.norm(np.subtract(P, points[ref]), axis=-1)
        r["difference"] = dict(reference=ref,
                               max_over_radius=float(d.max()) / r["radius"],
                               rms_over_radius=rms_distance(P, points[ref])
                               / r["radius"])


def plot(rec):
    """Time a step stacked by part, a bar a configuration (rank 0)."""
    import matplotlib.pyplot as plt

    ok = [r for r in rec["runs"] if "per_step_s" in r]
    failed = [r["config"] for r in rec["runs"] if "per_step_s" not in r]
    fig, ax = plt.subplots(figsize=(2.5 + 0.8 * len(ok), 4.5), layout="constrained")
    stacked_bars(ax, [r["config"] for r in ok], [r["per_step_s"] for r in ok])
    ax.tick_params(axis="x", labelrotation=45, labelsize=8)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1))
    ax.set_title(f"full model {rec['rows']}x{rec['cols']}, {rec['steps']} backward "
                 f"Euler steps, {rec['nproc']} rank(s)"
                 + (f"\nfailed: {', '.join(failed)}" if failed else ""), fontsize=9)
    save_figure(fig, rec["name"])


def report(comm, rec):
    """Print the tables; draw the figure on rank 0."""
    rows = []
    for r in rec["runs"]:
        d = r.get("difference", {})
        rows.append([r["config"], "failed: " + r["failed"] if "failed" in r else "ok",
                     1e3 * r["wall_s"]["run"] / r["steps"] if "steps" in r else "-",
                     r.get("newton", "-"), r.get("ksp", "-"),
                     r["memory"]["peak_rss_mib_max"] if "memory" in r else "-",
                     d.get("max_over_radius", "-")])
    PETSc.Sys.Print(markdown_table(["configuration", "result", "ms/step", "Newton its",
                                    "KSP its", "peak RSS [MiB]", "max diff / r"], rows))
    ok = [r for r in rec["runs"] if "per_step_s" in r]
    PETSc.Sys.Print(split_table([r["config"] for r in ok],
                                [r["per_step_s"] for r in ok]))
    if comm.rank == 0 and ok:
        plot(rec)


def main():
    comm = PETSc.COMM_WORLD
    opts = KnitOptions("bench_")
    sizes = sizes_option(opts, "15x30", "jersey size ROWSxCOLS")
    if len(sizes) != 1:
        raise KnitError("-bench_sizes: the solver sweep takes one size, e.g. 20x40 "
                        "(run it once a size, with -bench_tag)")
    (rows, cols), = sizes
    steps = opts.getInt("steps", 5, "backward Euler steps", 1)
    config = opts.getString("config", "", "run only this configuration, in this "
                            "process (what the sweep spawns)")
    names = opts.getString("configs", "", "configurations to sweep, a,b,... "
                           "(default: every solver_configs/*.rc)")
    nproc = opts.getInt("np", 1, "MPI ranks of each configuration", 1)
    timeout = opts.getReal("timeout", 900.0, "seconds before a configuration is "
                           "stopped", positive=True)
    reference = opts.getString("reference", "mumps_ldlt", "configuration the final "
                               "states are compared with")
    tag = opts.getString("tag", "", "suffix of the result and figure names")
    only_report = opts.getBool("plot", False, "only print the tables and draw the "
                               "figure of the JSON file")
    opts.printHelp(f"benchmarks.{STUDY} (and the -knit_ options of knitfem run)")
    name = STUDY + (f"_{tag}" if tag else "")
    if config:
        return child(comm, config, rows, cols, steps)
    if only_report:
        return report(comm, read_json(name))
    if PETSc.Options().hasName("help"):
        return
    if comm.size > 1:
        raise KnitError("run the sweep without mpirun; -bench_np P runs every "
                        "configuration on P ranks")
    known = configurations()
    chosen = names.split(",") if names else list(known)
    unknown = [c for c in chosen if c not in known]
    if unknown:
        raise KnitError(f"-bench_configs: no {', '.join(unknown)} in {CONFIGS}; "
                        f"use some of {', '.join(known)}")
    runs = [spawn(c, nproc, timeout) for c in chosen]
    compare(runs, reference)
    for r in runs:
        r["description"], r["rc"] = known[r["config"]]
    rec = record(comm, STUDY, name=name, rows=rows, cols=cols, steps=steps,
                 nproc=nproc, runs=runs)
    write_json(comm, name, rec)
    report(comm, rec)


if __name__ == "__main__":
    sys.exit(run(main, STUDY))
