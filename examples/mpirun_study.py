"""Where does a step's time go, and what do more ranks buy?

The full model's implicit step solves, at every Newton iteration, the
saddle point

    [K  Cᵀ] [δε]     [r_u]
    [C  0 ] [δλ] = − [r_λ],   K = M/(β h²) + ∂²E/∂ε² + ...,

K from the yarn elements' kernels (event knitTangent, within
SNESJacobianEval), the residual from their forces (knitForces), its
factorisation by MUMPS (MatCholFctrNum: LDLᵀ; MatLUFactorNum with LU) and
the triangular solves (MatSolve), all within SNESSolve.
PETSc times each event on every rank; this study runs the
hanging scene for a few steps and reads the times back, the way the
benchmarks do, with the slowest rank's figure for each event.

    mpirun -n 2 python examples/mpirun_study.py -log_view
    python examples/mpirun_study.py -log_view :log.txt

It writes study_np<ranks>.json (run it on 1 and 2 ranks and compare); with
-log_view PETSc prints its own table at the end, one stage a phase (Model
set-up, Solver set-up, Time stepping).
"""

import json
import sys

import petsc4py

petsc4py.init(sys.argv)

from mpi4py import MPI  # noqa: E402
from petsc4py import PETSc  # noqa: E402

import knitfem  # noqa: E402

PETSc.Log.begin()        # time events even without -log_view
comm = PETSc.COMM_WORLD
ROWS, COLS, T_END = 6, 12, 0.01

fabric = knitfem.scene("hanging", rows=ROWS, cols=COLS)
system = knitfem.full_model(fabric, knitfem.material("hanging"))
sim = knitfem.simulation(system, scene="hanging", verbose=False)   # no output
rec = sim.run(T_END)

# Event times are kept by stage: read those of the stage "Time stepping".
EVENTS = ("knitForces", "knitTangent", "SNESJacobianEval", "MatCholFctrNum",
          "MatLUFactorNum", "MatSolve", "SNESSolve")
stage = PETSc.Log.Stage("Time stepping").id
mpi = comm.tompi4py()
times = {name: mpi.allreduce(PETSc.Log.Event(name).getPerfInfo(stage)["time"],
                             op=MPI.MAX) for name in EVENTS}
study = dict(ranks=comm.size, rows=ROWS, cols=COLS, t_end=T_END,
             unknowns=rec["unknowns"], steps=rec["steps"],
             newton_iterations=rec["newton_iterations"],
             stepping_s=rec["wall_time_s"], event_time_s=times)
PETSc.Sys.Print(f"{comm.size} rank(s), {rec['unknowns']} unknowns: {rec['steps']} "
                f"steps, {rec['newton_iterations']} Newton iterations in "
                f"{rec['wall_time_s']:.2f} s")
for name, t in times.items():
    PETSc.Sys.Print(f"  {name:16s} {t:8.3f} s  {100 * t / rec['wall_time_s']:5.1f} %")
if comm.rank == 0:
    with open(f"study_np{comm.size}.json", "w") as f:
        json.dump(study, f, indent=1)
system.destroy()

# Things to try:
# - The speed-up: run on 1 and 2 ranks and divide the stepping times.
# - LU instead of LDLᵀ (from the repository's root): -options_file
#   benchmarks/solver_configs/mumps_lu.rc; a Krylov set-up for large knits
#   (whole-course Schwarz): -options_file benchmarks/solver_configs/krylov.rc.
# - A larger knit, where two ranks pay off: ROWS, COLS = 20, 40.
# - The reduced model's step (scene and sizes as here): knitfem.reduced_model;
#   its PtAP is the event knitPtAP.
# - A CSV of every event for a script: -log_view :log.csv:ascii_csv.
