"""Convergence in time: error of the centroid trajectory, order, work-precision.

    .venv/bin/python -m benchmarks.time_convergence -bench_plot
    .venv/bin/python -m benchmarks.time_convergence -bench_cases reduced -bench_plot

For each model (the reduced 7×7 hanging cloth, the full 3×3 swatch) with
no damping (-knit_damping 0), the mass-weighted centroid of the yarn
control points at t = 0.1, 0.2, 0.3 s is compared with a reference: the
BDF2 run at a fixed step ``-bench_ref_dt`` (1.25e-4 s), 8× below the
finest second-order step measured — a much finer run of the default
second-order method (L-stable, so no stiff mode is left ringing in it).
The error of a run is the largest distance |c(t) − c_ref(t)| over those
times, also given as a fraction of the centroid's largest displacement in
the reference (about 21 mm for the 7×7 cloth).

- Order: fixed steps ``-bench_dts`` (``-bench_dts_be`` for backward Euler,
  whose asymptotic range starts lower); the measured order
  is the least-squares slope of log(error) against log(dt) over them.
- Work-precision: error against wall time (and CPU time) of fixed-step
  backward Euler, generalized-α and BDF2, and of error-controlled BDF2 and
  generalized-α at the tolerances ``-bench_rtols`` (atol = rtol × 1e-2 m);
  and of the default options.
- Energy: T + E_el + E_g over ``-bench_energy_t`` (0.5 s) of the undamped
  run, each integrator at its default (error-controlled) settings; the
  drift is what summary.json reports as ``energy_drift``.

Writes ``benchmarks/results/time_convergence.json`` and, with -bench_plot,
``benchmarks/results/figures/time_convergence.png`` (order and
work-precision) and ``time_energy.png`` (with ``_reduced``/``_full``
appended when -bench_cases names one model). The machine is shared: the JSON
records wall and CPU time of every run.
"""

import time

import numpy as np

from .common import (PETSc, KnitOptions, forced, markdown_table, record, run,
                     save_figure, write_json)
from knitfem.cli.commands import (build_system, integrator_from_options,
                              jersey_from_options, material_from_options)
from knitfem.cli.scenes import make_fabric
from knitfem.run.simulation import Simulation
from solvers.integrators import SimulationError

INTEGRATORS = ("implicit", "alpha", "bdf2")
ADAPTIVE = ("bdf2", "alpha")
CASES = {"reduced": {"-knit_model": "reduced", "-knit_rows": "7", "-knit_cols": "7"},
         "full": {"-knit_model": "full", "-knit_rows": "3", "-knit_cols": "3"}}
TIMES = (0.1, 0.2, 0.3)


def trajectory(comm, options, times=TIMES, energy=False):
    """Centroid displacement (m) at ``times`` of the hanging scene under the
    -knit_ ``options``; with the run's steps, iterations, wall and CPU time."""
    opts = dict({"-knit_damping": "0"}, **options)
    with forced({k.lstrip("-"): v for k, v in opts.items()}):
        ko = KnitOptions()
        jersey = jersey_from_options(ko)
        fabric = make_fabric("hanging", jersey, tilt=90.0)
        system = build_system(comm, ko, fabric, material_from_options(ko))
        integrator = integrator_from_options(ko)(system)
    sim = Simulation(system, integrator, out=None, verbose=False,
                     output_every=1 if energy else 10**9)
    c0 = np.array(sim.measures()["centroid"])
    wall, cpu = time.perf_counter(), time.process_time()
    disp = []
    for t in times:
        rec = sim.run(t)
        disp.append(np.array(rec["centroid"]) - c0)
    out = dict(options=opts, disp=np.array(disp).tolist(), steps=rec["steps"],
               newton=rec["newton_iterations"], rejected=rec["rejected_steps"],
               wall_s=time.perf_counter() - wall, cpu_s=time.process_time() - cpu)
    if energy:
        out.update(energy_drift=rec["energy_drift"],
                   energy_drift_relative=rec["energy_drift_relative"],
                   energy_history=rec["energy_history"])
    system.destroy()
    return out


def error(run_, ref):
    """max_t |c(t) − c_ref(t)| (m)."""
    return float(np.linalg.norm(np.array(run_["disp"]) - np.array(ref["disp"]),
                                axis=1).max())


def order(dts, errors):
    """Least-squares slope of log(error) against log(dt)."""
    return float(np.polyfit(np.log(dts), np.log(errors), 1)[0])


def study(comm, case, steps, rtols, ref_dt, energy_t):
    base = CASES[case]
    PETSc.Sys.Print(f"{case}: reference, BDF2 dt = {ref_dt:g}")
    ref = trajectory(comm, dict(base, **{"-knit_integrator": "bdf2",
                                         "-knit_dt": str(ref_dt)}))
    scale = float(np.linalg.norm(ref["disp"], axis=1).max())
    rec = dict(reference=ref, displacement_scale=scale, fixed={}, adaptive=[])
    for name in INTEGRATORS:
        runs, dts = [], steps[name]
        for dt in dts:
            try:
                r = trajectory(comm, dict(base, **{"-knit_integrator": name,
                                                   "-knit_dt": str(dt)}))
            except SimulationError as err:
                PETSc.Sys.Print(f"  {name:8s} dt {dt:8.2e}  failed: {err}")
                continue
            r.update(dt=dt, error=error(r, ref))
            runs.append(r)
            PETSc.Sys.Print(f"  {name:8s} dt {dt:8.2e}  error {r['error']:.3e} m "
                            f"({100 * r['error'] / scale:6.3f} %)  newton "
                            f"{r['newton']:5d}  wall {r['wall_s']:6.2f} s")
        rec["fixed"][name] = dict(runs=runs, order=order([r["dt"] for r in runs],
                                                         [r["error"] for r in runs])
                                  if len(runs) > 1 else None)
    for name, rtol in ((n, t) for n in ADAPTIVE for t in rtols):
        if name != "bdf2" and rtol != rtols[-1]:
            continue
        r = trajectory(comm, dict(base, **{"-knit_integrator": name,
                                           "-knit_rtol": str(rtol),
                                           "-knit_atol": str(rtol * 1e-2)}))
        r.update(integrator=name, rtol=rtol, error=error(r, ref))
        rec["adaptive"].append(r)
        PETSc.Sys.Print(f"  {name:8s} rtol {rtol:8.1e}  error {r['error']:.3e} m "
                        f"({100 * r['error'] / scale:6.3f} %)  steps {r['steps']:5d} "
                        f"rejected {r['rejected']:3d}  newton {r['newton']:5d}  "
                        f"wall {r['wall_s']:6.2f} s")
    r = trajectory(comm, base)
    r.update(error=error(r, ref))
    rec["default"] = r
    PETSc.Sys.Print(f"  default options     error {r['error']:.3e} m "
                    f"({100 * r['error'] / scale:6.3f} %)  steps {r['steps']:5d}  "
                    f"wall {r['wall_s']:6.2f} s")
    rec["energy"] = {name: trajectory(comm, dict(base, **{"-knit_integrator": name}),
                                      times=(energy_t,), energy=True)
                     for name in INTEGRATORS}
    return rec


def plot(results, stem):
    import matplotlib.pyplot as plt

    cases = list(results)
    fig, axes = plt.subplots(2, len(cases), figsize=(6 * len(cases), 9), squeeze=False)
    labels = {"implicit": "backward Euler", "alpha": "generalized-α", "bdf2": "BDF2"}
    for j, case in enumerate(cases):
        rec, scale = results[case], results[case]["displacement_scale"]
        ax, wp = axes[0, j], axes[1, j]
        for name, fixed in rec["fixed"].items():
            dts = [r["dt"] for r in fixed["runs"]]
            err = [r["error"] / scale for r in fixed["runs"]]
            ax.loglog(dts, err, "o-",
                      label=f"{labels[name]} (order {fixed['order'] or 0:.2f})")
            wp.loglog([r["wall_s"] for r in fixed["runs"]], err, "o-",
                      label=f"{labels[name]}, fixed dt")
        for name in ADAPTIVE:
            ad = [r for r in rec["adaptive"] if r["integrator"] == name]
            wp.loglog([r["wall_s"] for r in ad], [r["error"] / scale for r in ad],
                      "s--", label=f"{labels[name]}, error-controlled")
        d = rec["default"]
        wp.loglog([d["wall_s"]], [d["error"] / scale], "k*", ms=14, label="default")
        for a in (ax, wp):
            a.axhline(0.02, color="grey", ls=":", lw=1)
            a.grid(True, which="both", alpha=0.3)
            a.legend(fontsize=8)
        ax.set(xlabel="dt [s]", ylabel="centroid error / largest displacement",
               title=f"{case} model: convergence in time")
        wp.set(xlabel="wall time [s]", ylabel="centroid error / largest displacement",
               title=f"{case} model: work-precision")
    save_figure(fig, stem)
    fig, axes = plt.subplots(1, len(cases), figsize=(6 * len(cases), 4), squeeze=False)
    for j, case in enumerate(cases):
        ax = axes[0, j]
        for name, r in results[case]["energy"].items():
            h = r["energy_history"]
            e0 = h["total"][0]
            ax.plot(h["t"], 1e6 * (np.array(h["total"]) - e0),
                    label=f"{labels[name]}: drift {r['energy_drift_relative']:.2%} "
                          "of max kinetic")
        ax.set(xlabel="t [s]", ylabel="E(t) − E(0) [µJ]",
               title=f"{case} model, no damping, default stepping")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    save_figure(fig, stem.replace("convergence", "energy"))


def main():
    comm = PETSc.COMM_WORLD
    opts = KnitOptions("bench_")
    cases = opts.getString("cases", "reduced,full", "models: reduced (7x7), full (3x3)")
    dts = [float(v) for v in opts.getString("dts", "4e-3,2e-3,1e-3",
                                            "fixed steps [s], second order").split(",")]
    dts_be = [float(v) for v in opts.getString("dts_be", "1e-3,5e-4,2.5e-4",
                                               "fixed steps [s], backward Euler")
              .split(",")]
    steps = dict(implicit=dts_be, alpha=dts, bdf2=dts)
    rtols = [float(v) for v in opts.getString("rtols", "1e-3,2e-4",
                                              "tolerances of the adaptive runs")
             .split(",")]
    ref_dt = opts.getReal("ref_dt", 1.25e-4, "step of the reference run [s]",
                          positive=True)
    energy_t = opts.getReal("energy_t", 0.3, "length of the energy runs [s]",
                            positive=True)
    draw = opts.getBool("plot", False, "draw the figures")
    opts.printHelp("benchmarks.time_convergence")
    results = {c: study(comm, c, steps, rtols, ref_dt, energy_t)
               for c in cases.split(",")}
    rows = []
    for case, rec in results.items():
        scale = rec["displacement_scale"]
        for name, fixed in rec["fixed"].items():
            rows.append([case, name, f"{fixed['order'] or 0:.2f}", ", ".join(
                f"{r['dt']:g} s: {100 * r['error'] / scale:.3f} % ({r['wall_s']:.1f} s)"
                for r in fixed["runs"])])
        for r in rec["adaptive"] + [dict(rec["default"], integrator="default")]:
            rows.append([case, f"{r['integrator']}, rtol {r.get('rtol', 'default')}",
                         "", f"{100 * r['error'] / scale:.3f} % ({r['steps']} steps, "
                         f"{r['rejected']} rejected, {r['newton']} Newton, "
                         f"{r['wall_s']:.1f} s)"])
    PETSc.Sys.Print(markdown_table(["model", "integrator", "order",
                                    "error (wall time)"], rows))
    name = "time_convergence" + ("" if cases == "reduced,full" else "_" + cases)
    write_json(comm, name,
               record(comm, "time_convergence", times=TIMES, dts=dts, rtols=rtols,
                      ref_dt=ref_dt, results=results))
    if draw and comm.rank == 0:
        plot(results, name)


if __name__ == "__main__":
    raise SystemExit(run(main, "time_convergence"))
