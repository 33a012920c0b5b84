"""Every -knit_ option a command's -help lists is named by a test, and the
ones no other test runs are run here for what they do: each test reads the
run's summary.json, output frames or messages, not only its exit status."""

import glob
import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest
from mpi4py import MPI

pytestmark = pytest.mark.skipif(MPI.COMM_WORLD.size > 1,
                                reason="runs knitfem in subprocesses")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SMALL = ("-knit_rows", "2", "-knit_cols", "2", "-knit_snapshots", "")
FIXED = ("-knit_integrator", "implicit", "-knit_dt", "1e-3")


def knitfem(out, *args, command="run"):
    """``knitfem command args -o out`` in a subprocess whose cache lies under
    ``out``'s parent; (process, summary.json as a dict or None)."""
    env = dict(os.environ, PYTHONPATH=ROOT,
               XDG_CACHE_HOME=str(out.parent / "cache"))
    p = subprocess.run([sys.executable, "-m", "knitfem.cli", command, *args,
                        "-o", str(out), "-skip_petscrc"], capture_output=True,
                       text=True, env=env, timeout=300)
    path = out / "summary.json"
    return p, json.loads(path.read_text()) if path.exists() else None


def listed_options():
    """{command: the -knit_ names its -help lists} (``declarations``)."""
    from knitfem.cli.main import COMMANDS
    from knitfem.cli.options import declarations

    return {c: [d.name for d in declarations(c) if d.name.startswith("knit_")]
            for c in COMMANDS}


def test_every_listed_option_is_named_by_a_test():
    """A test names an option as a string ("-knit_x" or "knit_x"): any that
    none names (a new one, say) fails here until a test runs it."""
    text = "".join(open(f).read() for f in glob.glob(os.path.join(ROOT, "tests",
                                                                   "*.py")))
    named = set(re.findall(r"""["']-?(knit_\w+)["']""", text))
    listed = listed_options()
    assert all(len(names) > 2 for names in listed.values()), listed
    missing = {c: sorted(set(names) - named) for c, names in listed.items()}
    assert not any(missing.values()), f"options no test names: {missing}"


# -- step control -------------------------------------------------------------
def test_first_and_largest_step(tmp_path):
    """-knit_dt_initial is the first trial step (accepted, the smallest of a
    smooth start) and -knit_dt_max bounds every step; by default they are
    1e-3 s and above 3e-3 s in this run."""
    _, default = knitfem(tmp_path / "a", *SMALL, "-knit_t_end", "0.02")
    _, bounded = knitfem(tmp_path / "b", *SMALL, "-knit_t_end", "0.02",
                         "-knit_dt_initial", "1e-5", "-knit_dt_max", "5e-4")
    assert default["dt_max"] > 3e-3 and default["dt_min"] > 5e-4
    assert bounded["dt_min"] == 1e-5  # the first step: the option's value, exactly
    assert bounded["dt_max"] <= 5e-4 * (1 + 1e-12)
    assert bounded["steps"] >= 0.02 / 5e-4


@pytest.mark.parametrize("option,other,loose", [("knit_rtol", "knit_atol", 4e-4),
                                                ("knit_atol", "knit_rtol", 2e-6)])
def test_tighter_local_error_takes_more_steps(tmp_path, option, other, loose):
    """The error norm's weight is w = atol + rtol |ε|: with the other
    tolerance negligible, one a hundred times tighter takes smaller steps
    (by about 100^(1/3) for a second-order method; |ε| ≈ 5 mm)."""
    recs = [knitfem(tmp_path / str(v), *SMALL, "-knit_t_end", "0.01", "-" + other,
                    "1e-14", "-" + option, str(v))[1] for v in (loose, loose / 100)]
    assert recs[1][option[5:]] == loose / 100
    assert recs[1]["steps"] > 2 * recs[0]["steps"]


def test_a_step_halved_below_dt_min_stops_the_run(tmp_path):
    """Newton failing (a one-iteration CG) halves the step: from 1e-3 s the
    second halving falls below -knit_dt_min 3e-4 s and the run stops, exit 3."""
    p, _ = knitfem(tmp_path / "a", *SMALL, "-knit_t_end", "0.01", "-knit_dt_min",
                   "3e-4", "-full_ksp_type", "cg", "-full_pc_type", "none",
                   "-full_ksp_max_it", "1")
    assert p.returncode == 3, p.stdout + p.stderr
    assert "the step fell below -knit_dt_min 0.0003 s" in p.stdout


def test_error_control_does_not_go_below_dt_min(tmp_path):
    """A local error tolerance no step above -knit_dt_min meets: the error
    control shrinks the step to dt_min, not below, and stops there, exit 3."""
    p, _ = knitfem(tmp_path / "a", *SMALL, "-knit_t_end", "0.002", "-knit_dt_min",
                   "1e-4", "-knit_rtol", "1e-10", "-knit_atol", "1e-13")
    assert p.returncode == 3, p.stdout + p.stderr
    assert re.search(r"local error \S+ times the tolerance at dt 1.00e-04 s; the "
                     r"step fell below -knit_dt_min 0.0001 s", p.stdout)


def test_a_crawling_run_stops_after_stall_steps(tmp_path):
    """Steps below 1e-5 t_end (here forced by -knit_dt_max) for
    -knit_stall_steps steps in a row stop the run, exit 3."""
    p, _ = knitfem(tmp_path / "a", *SMALL, "-knit_t_end", "0.02", "-knit_dt_max",
                   "1e-8", "-knit_stall_steps", "5")
    assert p.returncode == 3, p.stdout + p.stderr
    assert "step 5, t = 5e-08 s" in p.stdout and "crawls" in p.stdout


def test_drift_beyond_drift_tol_stops_the_run(tmp_path):
    """The constraints hold to ~1e-18 m: a -knit_drift_tol below that stops
    the first step, naming the option."""
    p, _ = knitfem(tmp_path / "a", *SMALL, *FIXED, "-knit_t_end", "0.005",
                   "-knit_drift_tol", "1e-30")
    assert p.returncode == 3, p.stdout + p.stderr
    assert re.search(r"step 1, .*constraint drift .* exceeds -knit_drift_tol 1e-30",
                     p.stdout)


@pytest.mark.parametrize("growth,said", [("0.5", "the total energy grew"),
                                         ("0", "(not finite|drift|SHAKE)")])
def test_energy_growth_guard(tmp_path, growth, said):
    """A symplectic step above its stable one: -knit_energy_growth 0.5 stops
    it at the energy's growth, 0 leaves it to blow up."""
    p, _ = knitfem(tmp_path / "a", "-knit_rows", "2", "-knit_cols", "1",
                   "-knit_snapshots", "", "-knit_EA", "5", "-knit_EI", "1e-6",
                   "-knit_scene", "freefall",
                   "-knit_integrator", "symplectic", "-knit_dt", "1e-4",
                   "-knit_unstable_dt", "-knit_t_end", "0.05", "-knit_output_every", "1",
                   "-knit_energy_growth", growth)
    assert p.returncode == 3, p.stdout + p.stderr
    assert re.search(said, p.stdout.splitlines()[-1])


def test_tangent_changes_iterations_not_states(tmp_path):
    """-knit_tangent mip and exact reach the same steps (to Newton's
    tolerance, 1e-9 r) in different iterations."""
    recs = [knitfem(tmp_path / t, *SMALL, *FIXED, "-knit_t_end", "0.003",
                    "-knit_tangent", t)[1] for t in ("exact", "mip")]
    # measured 2.0e-14
    assert np.allclose(recs[0]["centroid"], recs[1]["centroid"], rtol=0, atol=1.5e-13)
    assert recs[0]["newton_iterations"] != recs[1]["newton_iterations"]


def test_rho_inf_sets_the_numerical_dissipation(tmp_path):
    """Generalized-α without damping: -knit_rho_inf 1 keeps the energy far
    better than rho_inf 0, which damps the high modes at once."""
    drift = {}
    for rho in ("1", "0"):
        _, rec = knitfem(tmp_path / rho, *SMALL, "-knit_integrator", "alpha",
                         "-knit_dt", "1e-3", "-knit_t_end", "0.02", "-knit_damping",
                         "0", "-knit_rho_inf", rho, "-knit_yarn_contact", "off")
        drift[rho] = abs(rec["energy_drift_relative"])
    assert drift["1"] < 0.3 * drift["0"]      # measured 0.13


# -- the scene and the material --------------------------------------------------
def test_gravity_sets_the_fall(tmp_path):
    """Backward Euler's rigid fall: y_n = −g h² n(n + 1)/2 with g of
    -knit_gravity (measured to round-off)."""
    _, rec = knitfem(tmp_path / "a", *SMALL, *FIXED, "-knit_scene", "freefall",
                     "-knit_t_end", "0.01", "-knit_gravity", "2")
    # measured 7.0e-14
    assert rec["drop"] == pytest.approx(2 * 1e-6 * 10 * 11 / 2, rel=5e-13, abs=0)


def test_numpy_kernels_give_the_compiled_run(tmp_path):
    runs = [knitfem(tmp_path / k, *SMALL, *FIXED, "-knit_t_end", "0.005",
                    "-knit_kernels", k) for k in ("compiled", "numpy")]
    (_, compiled), (p, numpy_) = runs
    assert p.returncode == 0, p.stderr
    # measured 3.5e-18
    assert np.allclose(numpy_["centroid"], compiled["centroid"], rtol=0, atol=3e-17)


def catenary_sag(length, span):
    from scipy.optimize import brentq

    a = brentq(lambda a: 2 * a * np.sinh(span / (2 * a)) - length, span / 50, 1e3)
    return a * (np.cosh(span / (2 * a)) - 1)


def test_catenary_length_segments_and_load_steps(tmp_path):
    """The static catenary of -knit_length 0.09 on -knit_segments 12, solved
    in -knit_load_steps 3: 3 (12 + 3) coordinates, three load steps, the
    sag of a 0.09 m chain (1.8 % short on 12 segments, EI = 1e-10), not
    of the default 0.1 m one (0.0265 m)."""
    p, rec = knitfem(tmp_path / "a", "-knit_scene", "catenary", "-knit_static",
                     "-knit_length", "0.09", "-knit_segments", "12", "-knit_EI",
                     "1e-10", "-knit_load_steps", "3")
    assert p.returncode == 0, p.stdout + p.stderr
    assert "45 coordinates" in p.stdout
    assert re.findall(r"load step (\d)/3  load (\S+)", p.stdout) == [
        ("1", "0.33"), ("2", "0.67"), ("3", "1.00")]
    assert rec["sag"] == pytest.approx(catenary_sag(0.09, 0.08), rel=0.03)


def test_quadrature_converges(tmp_path):
    """-knit_quadrature n: Gauss points a segment change the run, less as
    n grows (the mass and stretch integrands are polynomial times |X'|)."""
    c = {n: np.array(knitfem(tmp_path / n, *SMALL, *FIXED, "-knit_t_end", "0.005",
                             "-knit_quadrature", n)[1]["centroid"])
         for n in ("2", "3", "6")}
    d2, d3 = np.abs(c["2"] - c["6"]).max(), np.abs(c["3"] - c["6"]).max()
    assert 0 < d3 < 0.1 * d2  # measured d3 = 0.024 d2


def test_pulled_stitch_moves_most(tmp_path):
    """-knit_pull_stitch c,r: of the loop heads of the swatch, that of the
    pulled stitch moved most (the free course's, one at each side of the
    middle)."""
    import h5py

    from knitfem.knit.pattern import Jersey

    jersey = Jersey(3, 4)
    heads = np.array([jersey.centreline(2 * np.pi * np.arange(4), r)
                      for r in range(3)])
    for c in (1, 2):
        out = tmp_path / str(c)
        p, _ = knitfem(out, "-knit_scene", "pulled", "-knit_rows", "3", "-knit_cols",
                       "4", *FIXED, "-knit_t_end", "0.005", "-knit_snapshots", "",
                       "-knit_output_every", "5", "-knit_pull_stitch", f"{c},0")
        assert p.returncode == 0, p.stderr
        frames = sorted(glob.glob(str(out / "yarns" / "0*.h5")))
        first, last = (h5py.File(f)["geometry"][:] for f in (frames[0], frames[-1]))
        near = np.argmin(np.linalg.norm(first - heads[..., None, :], axis=-1), axis=-1)
        moved = np.linalg.norm(last[near] - first[near], axis=-1)
        assert np.unravel_index(np.argmax(moved), moved.shape) == (0, c)


# -- bodies --------------------------------------------------------------------
def test_a_collider_stops_the_fall(tmp_path):
    """A free fall of 0.05 s drops 12.5 mm; -knit_collider's plane 0.3 mm
    below the yarn surface holds the yarns above it."""
    p, rec = knitfem(tmp_path / "a", *SMALL, *FIXED, "-knit_scene", "freefall",
                     "-knit_t_end", "0.05", "-knit_collider", "plane:0,-0.0035,0,0,1,0")
    assert p.returncode == 0, p.stdout + p.stderr
    assert rec["lowest_point"][1] - 5e-4 > -0.0035
    assert rec["drop"] < 0.5e-3


def test_friction_holds_a_yarn_on_a_slope(tmp_path):
    """Dropped on a plane sloping 20°, the swatch slides downhill without
    friction and far less with -knit_friction 1 > tan 20°."""
    dx = []
    for mu in ("0", "1"):
        p, rec = knitfem(tmp_path / mu, *SMALL, "-knit_integrator", "implicit",
                         "-knit_dt", "1e-3", "-knit_scene", "freefall", "-knit_t_end",
                         "0.1", "-knit_collider", "plane:0.002,-0.0065,0,0.342,0.940,0",
                         "-knit_friction", mu, "-knit_yarn_contact", "off")
        assert p.returncode == 0, p.stdout + p.stderr
        dx.append(rec["centroid"][0] - 0.002094)
    assert dx[0] > 1e-2 and abs(dx[1]) < 0.3 * dx[0]      # measured 1.4e-2, 0.16


# -- models --------------------------------------------------------------------
def test_volume_file_is_the_reduced_models_volume(tmp_path):
    """A 4 x 6 volume written to a file: the reduced run has its
    3 · 4 · 6 · 2 = 144 coordinates (150 with the default -knit_lod 5,5)."""
    from knitfem.cli.scenes import make_fabric
    from knitfem.knit.pattern import Jersey
    from knitfem.lod.volume import BoundingVolume

    fab = make_fabric("hanging", Jersey(2, 2), tilt=90.0)
    path = tmp_path / "volume.vtu"
    BoundingVolume.around(fab.X.reshape(-1, 3), 4, 6, margin=fab.radius).save(str(path))
    p, rec = knitfem(tmp_path / "a", *SMALL, *FIXED, "-knit_t_end", "0.003",
                     "-knit_model", "reduced", "-knit_sampling", "exact",
                     "-knit_volume", str(path))
    assert p.returncode == 0, p.stdout + p.stderr
    assert "reduced model, 144 coordinates" in p.stdout and rec["drop"] > 0


def test_full_regions_file_equals_the_region_option(tmp_path):
    """A -knit_full_regions file with one region (and a comment) gives the
    mixed run of -knit_full_region with that region."""
    path = tmp_path / "regions.txt"
    path.write_text("# the corner stitch\n0:1,0:1\n")
    args = (*SMALL, "-knit_cols", "3", *FIXED, "-knit_t_end", "0.003", "-knit_model",
            "mixed", "-knit_sampling", "exact")
    p, from_file = knitfem(tmp_path / "a", *args, "-knit_full_regions", str(path))
    q, from_option = knitfem(tmp_path / "b", *args, "-knit_full_region", "0:1,0:1")
    assert p.returncode == 0, p.stdout + p.stderr
    assert from_file["model"] == from_option["model"] == "mixed"
    assert from_file["unknowns"] == from_option["unknowns"]
    assert from_file["centroid"] == from_option["centroid"]


def test_sampling_tol_bounds_the_training_error(tmp_path):
    """-knit_sampling_tol: the sampled set's training error stays below it,
    with fewer elements for a looser one (48 elements in all here)."""
    recs = {}
    for tol in ("0.02", "0.002"):
        p, rec = knitfem(tmp_path / tol, *SMALL, "-knit_cols", "3", *FIXED,
                         "-knit_t_end", "0.002", "-knit_model", "reduced",
                         "-knit_sampling_tol", tol)
        assert p.returncode == 0, p.stdout + p.stderr
        recs[tol] = rec["sampling"]
        assert rec["sampling"]["tol"] == float(tol)
        assert rec["sampling"]["training_error"] <= float(tol)
    assert recs["0.02"]["elements"] < recs["0.002"]["elements"]


# -- adaptation ----------------------------------------------------------------
ADAPT = ("-knit_scene", "pulled", "-knit_rows", "6", "-knit_cols", "9", "-knit_lod",
         "6,5", "-knit_model", "mixed", "-knit_adapt", "-knit_pull_force",
         "0,-1e-3,0", "-knit_t_end", "0.005", "-knit_dt", "1e-3", "-knit_snapshots",
         "", "-knit_sampling", "exact", "-knit_adapt_coarsen", "1000")


@pytest.mark.parametrize("every,dwell", [(1, 2), (2, 1)])
def test_adaptation_refines_then_coarsens_after_its_dwell(tmp_path, every, dwell):
    """With -knit_adapt_coarsen 1000 r every yarn-level patch lies close
    enough to the volume: the pulled patch, refined at step 0, is coarsened
    at the first evaluation after -knit_adapt_dwell of them, evaluations
    every -knit_adapt_every steps: at step every (dwell + 1)."""
    p, rec = knitfem(tmp_path / "a", *ADAPT, "-knit_adapt_every", str(every),
                     "-knit_adapt_dwell", str(dwell))
    assert p.returncode == 0, p.stdout + p.stderr
    events = rec["adapt"]["events"]
    assert events[0]["step"] == 0 and events[0]["refined"] == [[1, 0]]
    assert events[1]["step"] == every * (dwell + 1)
    assert events[1]["coarsened"] == [[1, 0]] and events[1]["refined"] == []
    assert events[1]["unknowns"] == events[0]["unknowns"][::-1]


def test_adaptation_refines_only_above_its_threshold(tmp_path):
    """-knit_adapt_refine 1e6 (η never a million times its median): no
    patch is refined."""
    p, rec = knitfem(tmp_path / "a", *ADAPT, "-knit_adapt_refine", "1e6")
    assert p.returncode == 0, p.stdout + p.stderr
    assert rec["adapt"]["events"] == [] and rec["adapt"]["refine"] == 1e6
