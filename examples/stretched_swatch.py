"""A swatch relaxed, then stretched: the force–extension curve of a jersey.

A 5×5 jersey hangs from the loop heads of its top course. First it relaxes
under its own weight; then the loop head of its bottom course's middle
stitch is pulled down by a point force F, raised in steps. Each step is a
static equilibrium (quasi-static: no inertia, each solve starts from the
last one's shape),

    −Q(ε, 0) − F e_p + C(ε)ᵀμ = 0,      g(ε) = 0,

e_p the pulled point's B-spline weights. The question: how stiff is the
knit, and is it linear? A jersey is soft at first (its loops straighten
and slide into the pull) and stiffens as its yarns take the load.

    python examples/stretched_swatch.py [-static_snes_monitor]

It writes stretch.json, stretch.png (the curve) and stretched.png (the
swatch at the largest force).
"""

import json
import sys

import petsc4py

petsc4py.init(sys.argv)

import numpy as np  # noqa: E402
from petsc4py import PETSc  # noqa: E402

import knitfem  # noqa: E402
from knitfem.yarn.bspline import curve_points  # noqa: E402

FORCES = (0.0, 1e-3, 2e-3, 5e-3, 1e-2)   # pull [N]; 0: relaxed under gravity
ROWS = COLS = 5

curve, last = [], None
for F in FORCES:
    # The pulled scene of `knitfem run -knit_scene pulled`, its force ours.
    fabric = knitfem.scene("pulled", rows=ROWS, cols=COLS, pull_force=(0.0, -F, 0.0))
    system = knitfem.full_model(fabric)
    x = system.start_state()
    if last is not None:                 # quasi-static: from the last shape
        x.getArray()[:] = last
    x, newton = knitfem.equilibrium(system, x)
    last = x.getArray().copy()
    # The pulled point: the loop head, P(s) = Σ b_i(s) p_i on its course.
    yarn, s = fabric.loads[0][0], fabric.loads[1][0]
    P = knitfem.control_points(system, x)
    head = curve_points(P.yarn(yarn), np.atleast_1d(s))[0]
    curve.append(dict(force_N=F, pulled_point=head.tolist(), newton_iterations=newton))
    PETSc.Sys.Print(f"F = {1e3 * F:5.1f} mN: pulled point at y = {1e3 * head[1]:8.3f} "
                    f"mm ({newton} Newton iterations)")
    if F == FORCES[-1]:
        knitfem.picture("stretched.png", system, x,
                        title=f"{ROWS}x{COLS} jersey pulled by {1e3 * F:g} mN")
    system.destroy()

y = np.array([c["pulled_point"][1] for c in curve])
extension = y[0] - y                      # from the relaxed shape [m]
stiffness = np.diff(FORCES) / np.diff(extension)   # secant stiffness [N/m]
PETSc.Sys.Print("secant stiffness [N/m]: " + ", ".join(f"{k:.3g}" for k in stiffness))
if PETSc.COMM_WORLD.rank == 0:
    with open("stretch.json", "w") as f:
        json.dump(dict(rows=ROWS, cols=COLS, steps=curve,
                       extension_m=extension.tolist(),
                       secant_stiffness_N_per_m=stiffness.tolist()), f, indent=1)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5), dpi=110)
    ax.plot(1e3 * extension, 1e3 * np.array(FORCES), "o-")
    ax.set_xlabel("extension of the pulled loop [mm]")
    ax.set_ylabel("pull [mN]")
    ax.set_title(f"{ROWS}x{COLS} jersey, quasi-static pull")
    fig.tight_layout()
    fig.savefig("stretch.png")

# Things to try:
# - The reduced model (a volume cannot follow one loop: how much stiffer is
#   it?): system = knitfem.reduced_model(fabric); or the mixed model with
#   the yarn level around the pull, knitfem.mixed_model(fabric,
#   full_region="1:4,0:2").
# - Pull sideways: pull_force=(F, 0, 0); or another stitch, pull_stitch=(0, 0).
# - A stiffer yarn: knitfem.full_model(fabric, knitfem.material(EA=1000)).
# - Watch the continuation: -static_snes_monitor.
