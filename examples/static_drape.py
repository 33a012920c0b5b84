"""Static drape: a square of jersey hung by one corner.

The classic drape test: a 7×7 jersey held at the loop head of its top
course's first stitch hangs under its weight. No dynamics: its rest shape
solves the static equilibrium

    −Q(ε, 0) + C(ε)ᵀμ = 0,      g(ε) = 0,

(Q the elastic forces and gravity, g the knit's contacts and the held
point) by Newton with pseudo-transient continuation: each iteration is a
backward Euler step of the gradient flow M ε̇ = Q − Cᵀμ, its pseudo-time
step growing as the residual falls, so a knit at its stress-free rest,
whose courses hinge freely about their contacts, still finds its drape.

The question: how far does the corner-hung swatch sag, and how much of that
sag does the reduced model (ε = Γα) keep?

    python examples/static_drape.py [-static_snes_monitor]

It writes drape_full.png, drape_reduced.png and drape.json.
"""

import json
import sys

import petsc4py

petsc4py.init(sys.argv)

from petsc4py import PETSc  # noqa: E402

import knitfem  # noqa: E402

results = {}
for kind in ("full", "reduced"):
    # hold="corner" and tilt=0: hung by one corner, already hanging
    fabric = knitfem.scene("hanging", rows=7, cols=7, hold="corner", tilt=0)
    system = knitfem.full_model(fabric) if kind == "full" \
        else knitfem.reduced_model(fabric)
    x, newton = knitfem.equilibrium(system)
    # Sag: how far the lowest yarn point went down, in millimetres.
    sag = 1e3 * (knitfem.centrelines(system, system.start_state()).points[:, 1].min()
                 - knitfem.centrelines(system, x).points[:, 1].min())
    results[kind] = dict(newton_iterations=newton, sag_mm=float(sag),
                         unknowns=system.M.getSize()[0] + system.C.getSize()[0])
    PETSc.Sys.Print(f"{kind:8s} {results[kind]['unknowns']:6d} unknowns: "
                    f"{newton:4d} Newton iterations, sag {sag:.2f} mm")
    knitfem.picture(f"drape_{kind}.png", system, x, view="oblique",
                    title=f"corner-hung 7x7 jersey, {kind} model: sag {sag:.1f} mm")
    system.destroy()

results["sag_ratio"] = results["reduced"]["sag_mm"] / results["full"]["sag_mm"]
PETSc.Sys.Print(f"the reduced model keeps {100 * results['sag_ratio']:.0f} % of the "
                "full model's sag")
if PETSc.COMM_WORLD.rank == 0:
    with open("drape.json", "w") as f:
        json.dump(results, f, indent=1)

# Things to try:
# - Hold the whole top course instead: hold="top" (the curtain drape).
# - Follow the loading path: knitfem.equilibrium(system, load_steps=4).
# - Watch the continuation: -static_snes_monitor; change its solver with
#   -static_ksp_type, -static_pc_type.
# - A softer yarn bends more: -knit_EI 5e-9 (N m^2), or a finer volume for
#   the reduced model, -knit_lod 7,7.
# - The same drape from the command line (writes summary.json, a VTU, a PNG):
#   knitfem run -knit_hold corner -knit_tilt 0 -knit_static -o out/corner
