"""Garments: a tube knitted in the round, a sleeve on an arm, a swatch
draped on a sphere; full vs reduced model, wall time and shape difference.

    .venv/bin/python -m benchmarks.garments                      # every case
    .venv/bin/python -m benchmarks.garments -bench_cases tube,sleeve
    .venv/bin/python -m benchmarks.garments -bench_results benchmarks/results

Each case is a ``knitfem run`` command line exactly as the documentation
shows it (``COMMANDS``), run once as written (the reduced model: ``-knit_model
reduced``) and once with ``-knit_model full``, each into
out/benchmarks/garments/<case>_<model>. Per run: wall time of the whole process,
steps, Newton iterations, the summary's drop, sag, smallest distance to a
body and lowest point below it; per case: the reduced model's speed-up and
its shape difference from the full one at t_end (RMS and largest distance
between the two last frames' centreline points, the same samples in both,
and the centroid distance). Writes <results>/garments.json, each run's
snapshots as <results>/figures/garments_<case>_<model>.png (and its
animation, if it makes one, as .gif), and prints a markdown table; cases
not run keep their results in the JSON. The drape's and the elbow's full
runs take about 20 minutes each.
"""

import json
import os
import shutil
import subprocess
import sys
import time

import h5py
import numpy as np

from .common import (RESULTS, KnitError, KnitOptions, PETSc, markdown_table, read_json,
                     run, write_json)

STUDY = "garments"
KNITFEM = os.path.join(os.path.dirname(sys.executable), "knitfem")

# The documentation's garment commands, as written there (tests/
# test_doc_commands.py checks that every shown run with -knit_shape tube or
# -knit_scene drape is here).
COMMANDS = {
    "tube": "knitfem run -knit_scene hanging -knit_shape tube -knit_rows 10 "
            "-knit_cols 16 -knit_tilt 0 -knit_model reduced -knit_t_end 1 -o out/tube",
    "sleeve": "knitfem run -knit_scene freefall -knit_shape tube -knit_rows 10 "
              "-knit_cols 16 -knit_start_rotation 90,0,0 -knit_collider "
              "capsule:0,0.0115,-0.03,0,0.0115,0.03,0.007 -knit_friction 0.3 "
              "-knit_model reduced -knit_t_end 0.5 -knit_snapshots 0,0.5 -o out/sleeve",
    "drape": "knitfem run -knit_scene drape -knit_rows 12 -knit_cols 12 "
             "-knit_model reduced -knit_t_end 1 -knit_snapshots 0.3,1 -o out/drape",
    "elbow": "knitfem run -knit_scene sleeve -knit_rows 10 -knit_cols 16 "
             "-knit_model reduced -knit_t_end 0.5 -knit_snapshots 0,0.25,0.5 "
             "-knit_animation sleeve.gif -o out/elbow",
}


def with_model(command, model, out):
    """The command's words with -knit_model and -o replaced."""
    words = command.split()
    words[words.index("-knit_model") + 1] = model
    words[words.index("-o") + 1] = out
    return [KNITFEM] + words[1:]


def last_frame(out):
    """Centreline points (m, 3) of the last frame a run wrote."""
    frames = sorted(f for f in os.listdir(os.path.join(out, "yarns"))
                    if f[:-3].isdigit())
    with h5py.File(os.path.join(out, "yarns", frames[-1]), "r") as f:
        return f["geometry"][()]


def one_run(case, model, base):
    """Run the case's command with ``model`` into base/<case>_<model>; its
    snapshots go to <results>/figures/garments_<case>_<model>.png."""
    out = os.path.join(base, f"{case}_{model}")
    start = time.perf_counter()
    p = subprocess.run(with_model(COMMANDS[case], model, out), capture_output=True,
                       text=True)
    wall = time.perf_counter() - start
    if p.returncode != 0:
        return dict(model=model, failed=(p.stdout + p.stderr).strip().splitlines()[-1])
    for name in os.listdir(out):
        if name.endswith("_snapshots.png") or name.endswith(".gif"):
            os.makedirs(os.path.join(RESULTS, "figures"), exist_ok=True)
            shutil.copy(os.path.join(out, name), os.path.join(
                RESULTS, "figures", f"{STUDY}_{case}_{model}{name[-4:]}"))
    s = json.load(open(os.path.join(out, "summary.json")))
    keys = ("steps", "newton_iterations", "drop", "sag", "centroid",
            "min_collider_distance", "lowest_point_below_collider_centre")
    return dict(model=model, process_s=wall, **{k: s[k] for k in keys if k in s})


def compare(case, full, reduced, base):
    """Speed-up and shape difference of the reduced run from the full one."""
    if "failed" in full or "failed" in reduced:
        return {}
    a, b = (last_frame(os.path.join(base, f"{case}_{m}")) for m in ("full", "reduced"))
    d = np.linalg.norm(a - b, axis=1)
    return dict(speedup=full["process_s"] / reduced["process_s"],
                rms_distance=float(np.sqrt(np.mean(d ** 2))), max_distance=float(d.max()),
                centroid_distance=float(np.linalg.norm(
                    np.subtract(full["centroid"], reduced["centroid"]))))


def mm(v):
    return "-" if v is None else f"{1e3 * v:.2f}"


def main():
    opts = KnitOptions("bench_")
    raw = opts.getString("cases", ",".join(COMMANDS), "cases to run: "
                         + ",".join(COMMANDS))
    if opts.finish(f"benchmarks.{STUDY}"):
        return
    cases = [c for c in raw.split(",") if c]
    unknown = [c for c in cases if c not in COMMANDS]
    if unknown:
        raise KnitError(f"-bench_cases {','.join(unknown)}: use some of "
                        + ",".join(COMMANDS))
    base = os.path.join("out", "benchmarks", STUDY)      # the runs' own output
    rows, done = [], {}
    for case in cases:
        runs = {m: one_run(case, m, base) for m in ("full", "reduced")}
        cmp = compare(case, runs["full"], runs["reduced"], base)
        done[case] = dict(command=COMMANDS[case], **runs, comparison=cmp)
        for m, r in runs.items():
            rows.append([case, m, r.get("failed") or f"{r['process_s']:.1f} s",
                         r.get("steps", "-"), mm(r.get("drop")), mm(r.get("sag")),
                         mm(r.get("min_collider_distance")),
                         mm(r.get("lowest_point_below_collider_centre")),
                         f"{cmp['speedup']:.1f}x, RMS {mm(cmp['rms_distance'])} mm"
                         if cmp and m == "reduced" else ""])
    try:        # cases not run now keep their last results, read at the end:
        rec = read_json(STUDY)      # a study of other cases may have run meanwhile
    except OSError:
        rec = dict(study=STUDY, cases={})
    rec["cases"].update(done)
    write_json(PETSc.COMM_WORLD.tompi4py(), STUDY, rec)
    PETSc.Sys.Print(markdown_table(
        ["case", "model", "process", "steps", "drop (mm)", "sag (mm)",
         "min body distance (mm)", "lowest below body centre (mm)",
         "reduced vs full"], rows))


if __name__ == "__main__":
    sys.exit(run(main, STUDY))
