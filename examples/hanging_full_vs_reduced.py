"""Hanging swatch: the yarn-level model against its mechanical level of detail.

A 5×5 jersey held at the loop heads of its top course starts horizontal and
swings down under gravity. The full model integrates every yarn control
point, held together by the knit's contacts,

    M ε̈ = Q(ε, ε̇) + C(ε)ᵀλ,      g(ε) = 0,

the reduced one only the 5×5×2 control points α of a bounding volume in
which every yarn control point keeps its parameters, ε = Γα:

    M^V α̈ = Γᵀ Q(Γα, Γα̇) + (CΓ)ᵀλ,   M^V = Γᵀ M Γ.

The question: how far apart are the two swatches after the swing, in yarn
radii, and what does the reduced model save?

    python examples/hanging_full_vs_reduced.py
    mpirun -n 2 python examples/hanging_full_vs_reduced.py

It writes hanging_full/ and hanging_reduced/ (time series, summary.json and
a picture each) and comparison.json in the working directory.
"""

import json
import sys

import petsc4py

petsc4py.init(sys.argv)     # before knitfem builds anything: options count

import numpy as np  # noqa: E402
from petsc4py import PETSc  # noqa: E402

import knitfem  # noqa: E402

T_END = 0.3                 # simulated time [s]: the swatch has swung down
results, shapes = {}, {}
for kind in ("full", "reduced"):
    # The scene as `knitfem run -knit_scene hanging` builds it: tilted 90
    # degrees, held at its top course, with air drag (c_d = 1.4 1/s).
    fabric = knitfem.scene("hanging", rows=5, cols=5)
    material = knitfem.material("hanging")
    system = (knitfem.full_model if kind == "full" else knitfem.reduced_model)(
        fabric, material)
    # One directory a model: the time series yarns.xdmf, summary.json and a
    # PNG at T_END (hanging_t0.3s.png).
    sim = knitfem.simulation(system, out=f"hanging_{kind}", scene="hanging",
                             snapshots=(T_END,), verbose=False)
    rec = sim.run(T_END)
    shapes[kind] = knitfem.centrelines(sim).points   # (points, 3)
    results[kind] = {k: rec[k] for k in ("unknowns", "steps", "newton_iterations",
                                         "wall_time_s", "drop")}
    PETSc.Sys.Print(f"{kind:8s} {rec['unknowns']:6d} unknowns, {rec['steps']:4d} "
                    f"steps, {rec['wall_time_s']:6.2f} s, lowest point dropped "
                    f"{1e3 * rec['drop']:.2f} mm")
    system.destroy()

# The same material points on both: the centrelines are sampled alike.
gap = np.linalg.norm(shapes["full"] - shapes["reduced"], axis=-1)
results["max_distance_over_radius"] = float(gap.max() / fabric.radius)
results["speed_up"] = results["full"]["wall_time_s"] / results["reduced"]["wall_time_s"]
PETSc.Sys.Print(f"largest distance between the two swatches: "
                f"{results['max_distance_over_radius']:.2f} yarn radii; the "
                f"reduced model stepped {results['speed_up']:.1f}x faster")
if PETSc.COMM_WORLD.rank == 0:
    with open("comparison.json", "w") as f:
        json.dump(results, f, indent=1)

# Things to try:
# - A finer volume, closer to the yarns: -knit_lod 7,7 (the reduced model's
#   unknowns grow as 3·n1·n2·2).
# - Every yarn element instead of the trained sample: -knit_sampling exact.
# - A stiffer yarn, -knit_EA 1000, or a softer bend, -knit_EI 5e-9.
# - Watch each Newton solve: -full_snes_monitor -reduced_snes_monitor.
# - Open hanging_full/yarns.xdmf and hanging_reduced/yarns.xdmf in ParaView
#   side by side (Tube filter, radius from the "radius" array).
