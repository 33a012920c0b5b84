"""Shared machinery of the benchmark studies: set-up, PETSc log, records.

Every study runs as ``mpirun -n P .venv/bin/python -m benchmarks.<study>
[-bench_... options] [-knit_... options] [PETSc options]``. Importing this
module initialises PETSc from the command line and starts PETSc's default
log, so every stage and event is timed from the first object on.

``case`` builds a scene exactly as ``knitfem run`` does (the ``-knit_``
options and their defaults apply; a study forces some of them, such as
``-knit_model``, for one case only), runs a ``Simulation`` writing no files
and returns what was measured: wall times, Newton/KSP iterations, problem
sizes, the run's summary, peak memory, and the time, count and flops of the
PETSc events of each stage. ``record`` adds the machine, the PETSc version
and the command-line options; ``write_json`` and ``save_figure`` write, on
rank 0, to ``-bench_results DIR``: by default the scratch folder
``out/benchmarks/``, so a quick run never overwrites the committed results
(``-bench_results benchmarks/results`` writes those).

petsc4py 3.18 reads event figures with ``Log.Event(name).getPerfInfo(stage_id)``
(process-local, cumulative); it has no stage timer and no
``Sys.getMemoryUsage``, so stage wall times come from ``time.perf_counter``
and memory from ``getrusage`` (peak RSS) per rank.
"""

import json
import os
import platform
import resource
import sys
import time
from contextlib import contextmanager

import knitfem  # noqa: F401  (first: one BLAS thread per rank, as knitfem run)
import petsc4py

petsc4py.init(sys.argv)
from petsc4py import PETSc  # noqa: E402

PETSc.Log.begin()

import matplotlib  # noqa: E402
import numpy as np  # noqa: E402
from mpi4py import MPI  # noqa: E402

from knitfem.cli.commands import (build_system, jersey_from_options,  # noqa: E402
                                  material_from_options,
                                  start_rotation_from_options)
from knitfem.cli.options import KnitError, KnitOptions  # noqa: E402
from knitfem.io import atomic_write  # noqa: E402
from knitfem.cli.scenes import SCENES, make_fabric  # noqa: E402
from knitfem.run.simulation import Simulation  # noqa: E402
from solvers.integrators import INTEGRATORS, SimulationError  # noqa: E402

matplotlib.use("Agg")

__all__ = ["PETSc", "KnitError", "KnitOptions", "RESULTS", "case", "record", "run",
           "write_json", "read_json", "save_figure", "step_split", "split_table",
           "wall", "stacked_bars", "markdown_table", "sizes_option", "rms_distance",
           "drop"]

RESULTS = os.path.abspath(KnitOptions("bench_").getString(
    "results", os.path.join("out", "benchmarks"), "folder of the JSON results and "
    "figures (the committed ones: benchmarks/results)"))
COMMAND_LINE = PETSc.Options().getAll()
STAGES = ("Main Stage", "Model set-up", "Solver set-up", "Time stepping")
FACTOR = ("MatLUFactorSym", "MatILUFactorSym", "MatLUFactorNum", "MatCholFctrSym",
          "MatICCFactorSym", "MatCholFctrNum")
EVENTS = ("knitAssembly", "knitEmbedding", "knitForces", "knitTangent", "knitPtAP",
          "SNESSolve", "SNESFunctionEval", "SNESJacobianEval", "SNESLineSearch",
          "KSPSetUp", "KSPSolve", "PCSetUp", "PCApply", "MatSolve",
          "MatPtAPSymbolic", "MatPtAPNumeric", "MatConvert", "MatAXPY", "MatMult",
          *FACTOR)


# -- the machine and the run -----------------------------------------------
def machine():
    """Platform, CPU model, cores and total memory of this node."""
    def first(path, key):
        try:
            with open(path) as f:
                return next(line.split(":", 1)[1].strip() for line in f
                            if line.startswith(key))
        except (OSError, StopIteration):
            return None

    total = first("/proc/meminfo", "MemTotal")
    return dict(platform=platform.platform(), python=platform.python_version(),
                cpu=first("/proc/cpuinfo", "model name") or platform.processor(),
                cores=os.cpu_count(),
                memory_gib=round(int(total.split()[0]) / 2**20, 1) if total else None)


def memory(comm):
    """Peak resident set size (ru_maxrss, a high-water mark since the process
    started) in MiB, max and sum over the ranks (collective)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    mpi = comm.tompi4py()
    return dict(peak_rss_mib_max=mpi.allreduce(peak, op=MPI.MAX),
                peak_rss_mib_sum=mpi.allreduce(peak))


def record(comm, study, **fields):
    """The header every result file carries, then ``fields``."""
    return dict(study=study, machine=machine(),
                petsc=".".join(map(str, PETSc.Sys.getVersion())),
                petsc4py=petsc4py.__version__, ranks=comm.size,
                options=COMMAND_LINE, **fields)


# -- the PETSc log ---------------------------------------------------------
def log_snapshot():
    """This rank's cumulative {stage: {event: [time, count, flops]}}."""
    snap = {}
    for stage in STAGES:
        sid = PETSc.Log.Stage(stage).id
        snap[stage] = {}
        for name in EVENTS:
            info = PETSc.Log.Event(name).getPerfInfo(sid)
            snap[stage][name] = [info["time"], info["count"], info["flops"]]
    return snap


def log_since(before, comm):
    """Events that ran since ``before``, per stage: time (s, max over ranks),
    count (max), flops (sum) and, on more than one rank, each rank's time
    (``rank_times``). Collective."""
    after, mpi = log_snapshot(), comm.tompi4py()
    out = {}
    for stage, events in after.items():
        for name, (t, n, f) in events.items():
            t0, n0, f0 = before[stage][name]
            times = mpi.allgather(t - t0)
            n = mpi.allreduce(n - n0, op=MPI.MAX)
            f = mpi.allreduce(f - f0)
            if n:
                rec = dict(time=max(times), count=n, flops=f)
                if comm.size > 1:
                    rec["rank_times"] = times
                out.setdefault(stage, {})[name] = rec
    return out


SPLIT = ("forces", "residual other", "tangent", "PtAP", "Jacobian other",
         "PC set-up (factorisation)", "triangular solves", "Krylov, line search",
         "driver")


def step_split(rec):
    """Seconds a step in exclusive parts, from the "Time stepping" events.

    The forces and tangent kernels, the reduced model's PtAP, the rest of
    the residual and Jacobian callbacks, PCSetUp (the factorisations, also
    of fieldsplit blocks; SuperLU logs no MatLUFactor events), MatSolve, the
    rest of SNESSolve (Krylov iterations, line search, convergence test) and
    the driver outside SNESSolve (measures, gathers). KSPSolve is not
    subtracted: a fieldsplit's inner PCSetUp runs inside it.
    """
    ev = rec["log"].get("Time stepping", {})

    def t(*names):
        return sum(ev.get(name, {}).get("time", 0.0) for name in names)

    fun, jac = t("SNESFunctionEval"), t("SNESJacobianEval")
    parts = [t("knitForces"), fun - t("knitForces"), t("knitTangent"), t("knitPtAP"),
             jac - t("knitTangent", "knitPtAP"), t("PCSetUp"), t("MatSolve"),
             t("SNESSolve") - fun - jac - t("PCSetUp", "MatSolve"),
             rec["wall_s"]["run"] - t("SNESSolve")]
    return dict(zip(SPLIT, (p / max(rec["steps"], 1) for p in parts)))


# -- building and running a case -------------------------------------------
@contextmanager
def forced(values):
    """PETSc options set for the duration of a case, then restored."""
    db = PETSc.Options()
    saved = {k: db.getString(k) if db.hasName(k) else None for k in values}
    for k, v in values.items():
        db.setValue(k, v)
    try:
        yield
    finally:
        for k, v in saved.items():
            db.delValue(k)
            if v is not None:
                db.setValue(k, v)


def build(comm):
    """Fabric, system and integrator from the -knit_ options, as ``knitfem run``.

    Returns (system, integrator, wall seconds of the fabric, the model and the
    integrator set-up). Collective.
    """
    opts = KnitOptions()
    name = opts.getChoice("scene", "hanging", ("hanging", "freefall"), "scene")
    jersey = jersey_from_options(opts)
    params = SCENES[name].declare(opts, jersey)
    turn = start_rotation_from_options(opts)
    material = material_from_options(opts)
    dt = opts.getReal("dt", 1e-2, "time step [s]", positive=True)
    method = opts.getChoice("integrator", "implicit", tuple(INTEGRATORS), "integrator")
    tangent = opts.getChoice("tangent", "auto", ("auto", "exact", "mip"),
                             "Newton matrix, as knitfem run's -knit_tangent")
    clock = [time.perf_counter()]

    def lap():
        comm.barrier()
        clock.append(time.perf_counter())
        return clock[-1] - clock[-2]

    fabric = make_fabric(name, jersey, turn, **params)
    t_fabric = lap()
    system = build_system(comm, opts, fabric, material)
    t_model = lap()
    with PETSc.Log.Stage("Solver set-up"):
        integrator = (INTEGRATORS[method](system, dt) if method == "symplectic"
                      else INTEGRATORS[method](system, dt, tangent=tangent))
    return system, integrator, dict(fabric=t_fabric, model=t_model,
                                    integrator=lap())


def one_line(err):
    """The last non-empty line of an error (PETSc puts its reason there)."""
    lines = [s.strip() for s in str(err).splitlines() if s.strip()]
    return lines[-1] if lines else type(err).__name__


def case(comm, options, t_end=None, steps=None, points=False):
    """Build with the -knit_ ``options`` forced, simulate to ``t_end`` (or
    for ``steps`` steps of the integrator's dt).

    Returns the case record and, when ``points``, the control points at
    t_end on rank 0 (None elsewhere or on failure). A failed set-up or run
    is recorded as ``failed`` with its one-line reason. -bench_verbose prints
    knitfem's progress lines. Collective.
    """
    verbose = KnitOptions("bench_").getBool("verbose", False, "progress lines")
    before = log_snapshot()
    rec = dict(forced=dict(options))
    P = None
    with forced(options):
        try:
            comm.barrier()
            start = time.perf_counter()
            system, integrator, rec["wall_s"] = build(comm)
            n, k = system.M.getSize()[0], system.C.getSize()[0]
            rec.update(coordinates=n, constraints=k, unknowns=n + k,
                       radius=system.fabric.radius)
            sim = Simulation(system, integrator, out=None, verbose=verbose)
            summary = sim.run(t_end if steps is None else steps * integrator.dt)
            comm.barrier()
            rec["wall_s"].update(run=sim.wall_time, total=time.perf_counter() - start)
            rec.update(steps=summary["steps"], newton=summary["newton_iterations"],
                       ksp=summary["ksp_iterations"], summary=summary)
            if points:
                P = np.asarray(sim.geometry()[0]) if comm.rank == 0 else None
        except (SimulationError, PETSc.Error, KnitError) as err:
            rec["failed"] = one_line(err)
            PETSc.Sys.Print(f"  failed: {rec['failed']}")
    rec.update(memory=memory(comm), log=log_since(before, comm))
    return rec, P


# -- options, files, tables ------------------------------------------------
def run(main, study):
    """Run a study's ``main``; bad input ends it with one line, exit status 2."""
    try:
        return main() or 0
    except KnitError as err:
        PETSc.Sys.Print(f"benchmarks.{study}: error: {err}")
        return 2


def sizes_option(opts, default, text="jersey sizes ROWSxCOLS,..."):
    """-bench_sizes 7x7,15x30 as [(7, 7), (15, 30)]."""
    raw = opts.getString("sizes", default, text)
    try:
        sizes = [tuple(int(v) for v in s.split("x")) for s in raw.split(",") if s]
    except ValueError:
        sizes = []
    if not sizes or any(len(s) != 2 or min(s) < 1 for s in sizes):
        raise KnitError(f"-{opts.prefix}sizes {raw!r}: expected ROWSxCOLS,... "
                        "with positive integers, e.g. 7x7,15x30")
    return sizes


def write_json(comm, name, rec):
    """RESULTS/<name>.json, written whole by rank 0 (collective)."""
    if comm.rank == 0:
        os.makedirs(RESULTS, exist_ok=True)
        path = os.path.join(RESULTS, name + ".json")
        def dump(tmp):
            with open(tmp, "w") as f:
                json.dump(rec, f, indent=1)

        atomic_write(path, dump)        # a run stopped here leaves the old file
        PETSc.Sys.Print(f"wrote {os.path.relpath(path)}", comm=PETSc.COMM_SELF)
    comm.barrier()


def read_json(name):
    with open(os.path.join(RESULTS, name + ".json")) as f:
        return json.load(f)


def save_figure(fig, name):
    """RESULTS/figures/<name>.png (call on rank 0)."""
    import matplotlib.pyplot as plt

    path = os.path.join(RESULTS, "figures", name + ".png")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)
    PETSc.Sys.Print(f"wrote {os.path.relpath(path)}", comm=PETSc.COMM_SELF)


def stacked_bars(ax, labels, splits):
    """Bars of the time a step [ms], stacked by the parts of ``step_split``."""
    bottom = np.zeros(len(labels))
    for part in SPLIT:
        h = np.array([s[part] for s in splits]) * 1e3
        ax.bar(labels, h, bottom=bottom, label=part)
        bottom += h
    ax.set_ylabel("wall time a step [ms]")


def wall(r):
    """A case's total wall time, or why there is none."""
    return r.get("wall_s", {}).get("total") or r.get("failed") or r.get("skipped", "-")


def split_table(labels, splits):
    """Markdown table of the time a step [ms] by part, a row a label."""
    return markdown_table(["", *SPLIT, "total"],
                          [[label, *(1e3 * s[p] for p in SPLIT),
                            1e3 * sum(s.values())] for label, s in zip(labels, splits)])


def markdown_table(header, rows):
    """A markdown table (printed by the studies, pasted into the README)."""
    def cell(v):
        if isinstance(v, float):
            return f"{v:.3g}" if abs(v) < 100 else f"{v:.0f}"
        return str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def drop(summary, key="drop"):
    """The lowest point's fall of a run's summary, or with ``key``
    "drop_relative_difference" that of a comparison (results written before
    summary.json named it ``drop`` say ``sag``); "-" when absent."""
    return summary.get(key, summary.get(key.replace("drop", "sag"), "-"))


def rms_distance(P, Q):
    """RMS distance between two sets of points (…, 3)."""
    return float(np.sqrt(np.mean(np.sum((np.asarray(P) - np.asarray(Q))**2, -1))))
