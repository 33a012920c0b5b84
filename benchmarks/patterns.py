"""Stitch patterns relaxed side by side: jersey, 1×1 and 2×2 rib, garter and
seed at one loop length.

    .venv/bin/python -m benchmarks.patterns                       # 10x10 each
    .venv/bin/python -m benchmarks.patterns -bench_size 4x4 -bench_patterns rib1x1,jersey

Each pattern is ``knitfem relax -knit_pattern NAME`` of the same size, every
one at the loop length of the longest of their templates
(``-knit_loop_length``, so that they differ by their stitches alone and no
template is shrunk below its yarn's thickness), into out/benchmarks/patterns/
<name>. Per pattern, from its summary: course and wale spacings (mean
distances between neighbouring loop heads), Munden's k_c, k_w, k_s, the curl
of each edge, the smallest gap between yarns (×2r), steps and the whole
process's wall time. Each relaxed swatch is then stretched quasi-statically
along its courses and along its wales (``knitfem.run.tensile``: its edge
loop heads clamped, one clamp pulled through the strains
``-bench_strains``): the force against strain and the initial tensile
stiffness per unit width of the clamped edge. Writes
<results>/patterns.json (patterns not run keep their last results) and
prints a markdown table. A textile reading: a 1×1 rib draws in across its
width (wale spacing below jersey's), garter along its length (course
spacing below jersey's).
"""

import json
import os
import subprocess
import sys
import time

from .common import (KnitError, KnitOptions, PETSc, markdown_table, read_json, run,
                     write_json)

STUDY = "patterns"
KNITFEM = os.path.join(os.path.dirname(sys.executable), "knitfem")
PATTERNS = ("rib1x1", "jersey", "rib2x2", "garter", "seed")


def relax(name, size, loop_length, base):
    """One relaxation: the record of its summary (or why it failed)."""
    out = os.path.join(base, name)
    words = [KNITFEM, "relax", "-knit_pattern", name, "-knit_rows", str(size[0]),
             "-knit_cols", str(size[1]), "-o", out]
    if loop_length:
        words += ["-knit_loop_length", repr(loop_length)]
    start = time.perf_counter()
    p = subprocess.run(words, capture_output=True, text=True)
    rec = dict(command=" ".join(["knitfem"] + words[1:]),
               process_s=time.perf_counter() - start)
    if p.returncode:
        return dict(rec, failed=(p.stdout + p.stderr).strip().splitlines()[-1])
    with open(os.path.join(out, "summary.json")) as f:
        s = json.load(f)
    return dict(rec, **{k: s.get(k) for k in (
        "chart", "loop_length_m", "course_spacing_m", "wale_spacing_m", "k_c", "k_w",
        "k_s", "curl", "min_yarn_gap", "steps", "settled")})


def template_loop(name, size):
    """The loop length [m] of the pattern's template."""
    from knitfem.knit.chart import named_chart
    from knitfem.knit.pattern import Jersey, jersey_fabric
    from knitfem.run.relax import stitch_length

    jersey = Jersey(*size, chart=named_chart(name, *size))
    return float(f"{stitch_length(jersey, jersey_fabric(jersey)):.4g}")


def tensile(name, size, base, strains):
    """The relaxed swatch ``name`` stretched along its courses and its wales
    (``knitfem.run.tensile.stretch``): {direction: record}."""
    from knitfem.knit.chart import named_chart
    from knitfem.knit.pattern import Jersey
    from knitfem.run.relax import RelaxedKnit
    from knitfem.run.tensile import DIRECTIONS, stretch

    knit = RelaxedKnit.load(os.path.join(base, name, "relaxed.h5"))
    jersey = Jersey(*size, knit.radius, knit=knit.shape, rest=knit,
                    chart=named_chart(name, *size))
    out = {}
    for along in DIRECTIONS:
        start = time.perf_counter()
        out[along] = dict(stretch(PETSc.COMM_SELF, jersey, along, strains),
                          wall_s=time.perf_counter() - start)
    return out


def main():
    opts = KnitOptions("bench_")
    raw = opts.getString("patterns", ",".join(PATTERNS), "patterns to relax, the "
                         "first setting the loop length: " + ",".join(PATTERNS))
    size = opts.getString("size", "10x10", "courses x stitches of every swatch")
    strains = opts.getReals("strains", (0.005, 0.01, 0.02), "the three nominal "
                            "strains the tensile test pulls each relaxed swatch "
                            "through, increasing", 3)
    if opts.finish(f"benchmarks.{STUDY}"):
        return
    names = [n for n in raw.split(",") if n]
    unknown = [n for n in names if n not in PATTERNS]
    if unknown or not names:
        raise KnitError(f"-bench_patterns {raw}: use some of " + ",".join(PATTERNS))
    try:
        size = tuple(int(v) for v in size.split("x"))
        assert len(size) == 2 and min(size) >= 3
    except (ValueError, AssertionError):
        raise KnitError(f"-bench_size {size}: expected ROWSxCOLS, each at least 3"
                        ) from None
    base = os.path.join("out", "benchmarks", STUDY)
    try:
        rec = read_json(STUDY)
    except OSError:
        rec = dict(study=STUDY, patterns={})
    loop_length = max(template_loop(name, size) for name in names)
    for name in names:
        r = relax(name, size, loop_length, base)
        if "failed" not in r:
            r["tensile"] = tensile(name, size, base, strains)
        rec["patterns"][name] = dict(r, size=list(size))
        PETSc.Sys.Print(f"{name}: {r.get('failed') or 'relaxed'} in "
                        f"{r['process_s']:.0f} s")
    write_json(PETSc.COMM_WORLD.tompi4py(), STUDY, rec)
    rows = []
    for name, r in rec["patterns"].items():
        curl = r.get("curl") or {}
        rows.append([name, "x".join(map(str, r["size"])),
                     r.get("failed") or f"{1e3 * r['loop_length_m']:.2f}",
                     *(f"{1e3 * r[k]:.2f}" if r.get(k) else "-"
                       for k in ("course_spacing_m", "wale_spacing_m")),
                     *(f"{r[k]:.2f}" if r.get(k) else "-" for k in ("k_c", "k_w")),
                     ", ".join(f"{e} {c['side']} {abs(c['angle_deg']):.0f}°"
                               for e, c in curl.items()),
                     f"{r['min_yarn_gap']:.3f}" if r.get("min_yarn_gap") else "-",
                     *(f"{r['tensile'][d]['stiffness_N_per_m']:.2f}" if r.get("tensile")
                       else "-" for d in ("courses", "wales")),
                     f"{r['process_s']:.0f} s"])
    PETSc.Sys.Print(markdown_table(
        ["pattern", "size", "loop length (mm)", "courses (mm)", "wales (mm)", "k_c",
         "k_w", "curl", "gap (2r)", "courses: E (N/m)", "wales: E (N/m)",
         "process"], rows))


if __name__ == "__main__":
    sys.exit(run(main, STUDY))
