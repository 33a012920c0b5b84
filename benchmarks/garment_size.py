"""Garments against their size: the cost of a Newton iteration, the set-up,
the steps and the memory of the sleeve and the drape as the yarns and the
volume grow.

    .venv/bin/python -m benchmarks.garment_size                   # every case
    .venv/bin/python -m benchmarks.garment_size -bench_cases sleeve_60x120_reduced
    .venv/bin/python -m benchmarks.garment_size -bench_window 0.1
    .venv/bin/python -m benchmarks.garment_size -bench_results benchmarks/results

Each case is a ``knitfem run`` command line (``CASES``) run for the first
``-bench_window`` seconds (0.05 by default: the fall onto the body and the
landing) in a process of its own, with ``-log_view``; the sleeve's elbow
bends over 0.5 s whatever the window (``-knit_elbow_time 0.5``), so every
window is the start of the same run. Per case: the whole process's wall
time and peak memory (the child's ``ru_maxrss``), the PETSc stages "Model
set-up", "Solver set-up" and "Time stepping", the steps and Newton
iterations, the time stepping's seconds a Newton iteration, the yarn control
points, the unknowns and, for a reduced model, its volume control points;
where a size runs in both models, the reduced model's shape difference from
the full one at the window's end (``garments.compare``: the speed-up, RMS
and largest distance of the centreline samples, centroid distance); the
integrator and its steps (the accuracy behind the times: fixed backward
Euler steps of 1e-2 s for a reduced model on bodies, error-controlled BDF2
for the full one). Writes
<results>/garment_size.json and prints a markdown table; cases not run keep
their results in the JSON.
"""

import json
import os
import re
import subprocess
import sys
import time

from .common import (KnitError, KnitOptions, PETSc, markdown_table, read_json, run,
                     write_json)
from .garments import compare

STUDY = "garment_size"
KNITFEM = os.path.join(os.path.dirname(sys.executable), "knitfem")
SLEEVE = "knitfem run -knit_scene sleeve -knit_elbow_time 0.5"
DRAPE = "knitfem run -knit_scene drape"
CASES = {
    "sleeve_16x10_full": f"{SLEEVE} -knit_rows 10 -knit_cols 16 -knit_model full",
    "sleeve_16x10_reduced": f"{SLEEVE} -knit_rows 10 -knit_cols 16 -knit_model reduced",
    "sleeve_60x120_reduced": f"{SLEEVE} -knit_rows 120 -knit_cols 60 -knit_model reduced",
    "sleeve_120x240_reduced": f"{SLEEVE} -knit_rows 240 -knit_cols 120 -knit_model reduced",
    "drape_12x12_full": f"{DRAPE} -knit_rows 12 -knit_cols 12 -knit_model full",
    "drape_12x12_reduced": f"{DRAPE} -knit_rows 12 -knit_cols 12 -knit_model reduced",
    "drape_60x60_reduced": f"{DRAPE} -knit_rows 60 -knit_cols 60 -knit_model reduced",
}
STAGES = ("Model set-up", "Solver set-up", "Time stepping")


def stage_times(path):
    """Seconds of each stage in the "Summary of Stages" of a -log_view file."""
    out = {}
    with open(path) as f:
        for line in f:
            m = re.match(r"\s*\d+:\s+(.+?):\s+([0-9.]+e[+-]\d+)", line)
            if m and m.group(1) in STAGES:
                out[m.group(1)] = float(m.group(2))
    return out


def one_case(name, window, base):
    """Run the case for ``window`` seconds into base/<name>: its record."""
    out = os.path.join(base, name)
    log = out + ".log_view"
    words = CASES[name].split()[1:] + [
        "-knit_t_end", f"{window:g}", "-knit_snapshots", f"{window:g}", "-o", out,
        "-log_view", f":{log}"]
    start = time.perf_counter()
    child = subprocess.Popen([KNITFEM] + words, stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True)
    text = child.stdout.read()
    _, status, usage = os.wait4(child.pid, 0)
    wall = time.perf_counter() - start
    if status != 0:
        return dict(command=CASES[name], failed=text.strip().splitlines()[-1])
    s = json.load(open(os.path.join(out, "summary.json")))
    stages = stage_times(log)
    rec = dict(command=CASES[name], model=s["model"], window_s=window, process_s=wall,
               memory=dict(peak_rss_mib_max=usage.ru_maxrss / 1024), stages_s=stages,
               steps=s["steps"], newton=s["newton_iterations"],
               rejected=s["rejected_steps"], drop=s["drop"], centroid=s["centroid"],
               unknowns=s["unknowns"], yarn_control_points=s["yarn_control_points"],
               newton_s=stages.get("Time stepping", 0.0) / max(s["newton_iterations"], 1),
               min_collider_distance=s.get("min_collider_distance"),
               **{k: s[k] for k in ("integrator", "adaptive", "dt_min", "dt_max")})
    if s["model"] == "reduced":
        rec["volume_control_points"] = s["unknowns"] // 3
    return rec


def main():
    opts = KnitOptions("bench_")
    raw = opts.getString("cases", ",".join(CASES), "cases to run: " + ",".join(CASES))
    window = opts.getReal("window", 0.05, "simulated seconds a case [s]", positive=True)
    if opts.finish(f"benchmarks.{STUDY}"):
        return
    cases = [c for c in raw.split(",") if c]
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        raise KnitError(f"-bench_cases {','.join(unknown)}: use some of " + ",".join(CASES))
    base = os.path.join("out", "benchmarks", STUDY)
    try:                           # cases not run now keep their last results
        rec = read_json(STUDY)
    except OSError:
        rec = dict(study=STUDY, cases={})
    for name in cases:
        rec["cases"][name] = one_case(name, window, base)
    for name in list(rec["cases"]):    # each size run now in both models
        size = name[:-len("_full")]
        full, reduced = rec["cases"][name], rec["cases"].get(size + "_reduced")
        if name.endswith("_full") and {name, size + "_reduced"} <= set(cases) and \
                full.get("window_s") == reduced.get("window_s"):
            reduced["against_full"] = compare(size, full, reduced, base)
    write_json(PETSc.COMM_WORLD.tompi4py(), STUDY, rec)
    rows = []
    for name, r in rec["cases"].items():
        if "failed" in r:
            rows.append([name, r["failed"]] + [""] * 9)
            continue
        st, cmp = r["stages_s"], r.get("against_full")
        rows.append([name, r["yarn_control_points"], r.get("volume_control_points", "-"),
                     r["unknowns"], f"{st.get('Model set-up', 0) + st.get('Solver set-up', 0):.1f}",
                     r["steps"], r["newton"], f"{r['newton_s']:.3f}",
                     f"{r['process_s']:.1f}", f"{r['memory']['peak_rss_mib_max']:.0f}",
                     f"{1e3 * cmp['rms_distance']:.3f}" if cmp else ""])
    PETSc.Sys.Print(markdown_table(
        ["case", "yarn control points", "volume control points", "unknowns",
         "set-up (s)", "steps", "Newton its", "s / Newton it", "process (s)",
         "peak memory (MiB)", "RMS from full (mm)"], rows))


if __name__ == "__main__":
    sys.exit(run(main, STUDY))
