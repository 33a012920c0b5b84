"""The mixed model: all full ≡ the full model, none ≡ the reduced model, a
partial region exact on its linear map, and np = 2 ≡ np = 1."""

import numpy as np
import pytest
from petsc4py import PETSc

from helpers import COMM, gather, jersey, mixed, models, region, run, to_scipy
from knitfem.contact import constraints as cons
from knitfem.lod.mixed import VolumeWeights, parse_regions
from knitfem.errors import KnitError
from solvers.integrators import BackwardEuler

SELF = PETSc.COMM_SELF


LOD = (5, 5)       # 2 x 2 patches of 3 x 3 stitches


@pytest.fixture(scope="module")
def fabric():
    return jersey(6, 6, hold="top")


@pytest.fixture(scope="module")
def serial(fabric):
    full, red = models(SELF, fabric, lod=LOD)
    yield full, red
    red.destroy()
    full.destroy()


def states(system, nsteps=5, dt=1e-3):
    _, x, _ = run(system, BackwardEuler, dt, nsteps)
    return gather(system.comm, system.full_state(x))


@pytest.fixture(scope="module")
def motions(serial):
    """ε after ``states``' steps of the full and the reduced model."""
    full, red = serial
    return dict(full=states(full), reduced=states(red))


def test_all_full_is_the_full_model(serial, fabric, motions):
    full, red = serial
    mix = mixed(full, red, np.ones(fabric.npoints, bool))
    G = to_scipy(mix.space.Gamma).toarray()
    assert np.array_equal(G, np.eye(len(G)))             # Γ_mix = I, no α left
    x, xf = mix.start_state(), full.start_state()
    for name in ("M", "C"):
        mix.constraint_jacobian(x), full.constraint_jacobian(xf)
        A, B = to_scipy(getattr(mix, name)), to_scipy(getattr(full, name))
        assert abs(A - B).max() <= 1e-15 * abs(B).max()
    g, gf = mix.C.createVecLeft(), full.C.createVecLeft()
    x.getArray()[:] += 1e-2 * fabric.radius      # g itself, off the rest
    xf.getArray()[:] = x.getArray()
    mix.constraint_residual(x, g), full.constraint_residual(xf, gf)
    # measured 0
    assert np.allclose(g.getArray(), gf.getArray(), rtol=0, atol=3e-17 * fabric.radius)
    eps = states(mix)
    ref = motions["full"]
    assert np.abs(ref - fabric.X.ravel()).max() > 0.1 * fabric.radius   # it moved
    assert np.allclose(eps, ref, rtol=0, atol=2e-13 * fabric.radius)  # measured 0


def test_none_full_is_the_reduced_model(serial, fabric, motions):
    full, red = serial
    mix = mixed(full, red, np.zeros(fabric.npoints, bool))
    G, Gr = to_scipy(mix.space.Gamma), to_scipy(red.embedding.Gamma)
    assert G.shape == Gr.shape and abs(G - Gr).max() == 0
    assert abs(to_scipy(mix.M) - to_scipy(red.M)).max() <= 1e-15 * abs(
        to_scipy(red.M)).max()
    assert mix.contacts_kept == 0 and mix.world_rank == red.world_rank
    eps = states(mix)
    ref = motions["reduced"]
    assert np.abs(ref - fabric.X.ravel()).max() > 0.01 * fabric.radius
    assert np.allclose(eps, ref, rtol=0, atol=1e-10 * fabric.radius)


def test_partial_region_map_and_constraints(serial, fabric, motions):
    """Identity rows for full points, Γ rows for the rest; affine maps stay
    in range(Γ_mix); kept contacts are those with a side at least half full,
    and every kept constraint holds at rest."""
    full, red = serial
    mask = region(full, red, [(0, 2, 1, 2)])
    assert 0 < mask.sum() < 0.5 * mask.size
    mix = mixed(full, red, mask)
    G, Gr = to_scipy(mix.space.Gamma_scalar), to_scipy(red.embedding.Gamma_scalar)
    sp_ = mix.space
    # measured 4.4e-16
    assert np.allclose(np.asarray(G.sum(1)).ravel(), 1, rtol=0, atol=5e-15)
    F = np.flatnonzero(mask)
    assert np.array_equal(G[F][:, sp_.fullcol[F]].toarray(), np.eye(len(F)))
    E = np.flatnonzero(~mask)
    assert abs(G[E][:, sp_.volcol[sp_.alpha]] - Gr[E][:, sp_.alpha]).max() == 0
    # rest state, and an affine motion of q moves ε by the same map
    q = mix.rest_state()
    X = fabric.X.reshape(-1, 3)
    assert np.allclose(mix.full_state(q).getArray(), X.ravel(), rtol=0,
                       atol=2e-13 * fabric.radius)  # measured 6.9e-18
    A = np.array([[1.1, 0.2, -0.1], [0.05, 0.9, 0.3], [0.0, -0.2, 1.2]])
    qa = q.getArray().reshape(-1, 3)
    qa[:] = qa @ A.T + 1e-3
    assert np.allclose(mix.full_state(q).getArray().reshape(-1, 3), X @ A.T + 1e-3,
                       rtol=0, atol=2e-16)  # measured 1.7e-17
    contacts, _ = cons.build(fabric)
    side = np.zeros((contacts.count, 2))
    for i in range(contacts.count):       # each side's curve-point weights
        w = np.abs(contacts.U[i, 0])
        full_w = mask[contacts.cols[i]] * w
        side[i] = full_w[:4].sum() / w[:4].sum(), full_w[4:].sum() / w[4:].sum()
    assert mix.contacts_kept == np.sum(side.max(1) >= 0.5) > 0
    assert mix.contacts_kept < contacts.count
    r = mix.C.createVecLeft()
    mix.constraint_residual(mix.rest_state(), r)
    assert r.norm(PETSc.NormType.INFINITY) < 1e-15
    # its motion lies between the two models': it moves more than the
    # reduced model and less than the full one, |ε − X| = 1.86e-4 < 2.59e-4 <
    # 1.34e-3 m (measured), and in its full region it is nearer the full
    # model than the reduced one is (3.71e-4 against 4.03e-4 m)
    eps = states(mix)
    X, f, r = fabric.X.ravel(), motions["full"], motions["reduced"]
    assert np.linalg.norm(r - X) < np.linalg.norm(eps - X) < np.linalg.norm(f - X)
    near = np.repeat(mask, 3)
    assert np.linalg.norm((eps - f)[near]) < 0.95 * np.linalg.norm((r - f)[near])


def test_parallel_equals_serial(fabric):
    """np = 2 ≡ np = 1 (run under mpirun -n 2 by ``make test``)."""
    out = []
    for comm in (COMM, SELF):
        full, red = models(comm, fabric, lod=LOD)
        out.append(states(mixed(full, red, region(full, red, [(4, 5, 4, 6)]))))
    assert np.abs(out[1] - fabric.X.ravel()).max() > 1e-3 * fabric.radius
    # measured 3.5e-16 to 6.9e-16 m (1.4e-12 r) over five runs on 2 ranks
    assert np.allclose(out[0], out[1], rtol=0, atol=1e-11 * fabric.radius)


@pytest.mark.parametrize("text", ["0:2", "2:1,0:1", "0:2,0:9", "a:b,0:1"])
def test_bad_region_is_one_line(text):
    with pytest.raises(KnitError, match="c0:c1,r0:r1|outside|empty"):
        parse_regions(text, "-knit_full_region", 3, 4)


# -- point loads, the indicator, adaptation ------------------------------------
def test_point_load_vector_sums_to_the_force():
    """Σ_a b_a(u) F over the four control points is F (partition of unity),
    and its moment about the origin is P(s) × F (linear precision)."""
    from knitfem.knit.pattern import Jersey
    from knitfem.cli.scenes import pulled

    j = Jersey(3, 4)
    F = np.array([0.1, -0.3, 0.2])
    fab = pulled(j, (2, 1), F)
    Q = fab.load_vector(0, fab.nyarn)
    assert np.allclose(Q.sum(0), F, rtol=0, atol=2e-16)  # measured 2.8e-17 (|F| 0.3)
    X = fab.X.reshape(-1, 3)
    P = X[np.abs(Q).sum(1) > 0].T @ np.abs(Q[np.abs(Q).sum(1) > 0, :1]) / abs(F[0])
    from knitfem.yarn import bspline
    head = bspline.curve_points(fab.yarn(1), j.heads(1)[[2]])[0]
    assert np.allclose(P.ravel(), head, rtol=0, atol=6e-18)  # measured 8.7e-19 (an ulp)
    with pytest.raises(ValueError, match="outside"):
        pulled(j, (4, 0), F)


def indicator(fabric, lod=LOD):
    from knitfem.lod.adapt import Indicator

    full, red = models(COMM, fabric, lod=lod)
    return full, red, Indicator(full, red.embedding,
                                VolumeWeights(fabric, red.embedding.volume))


def test_indicator_vanishes_in_range_and_sees_a_point_load():
    """Free fabric at rest under gravity: the full model's acceleration is g
    everywhere, in range(Γ), so η = 0 and δ = 0 to round-off. A point load
    makes η largest on the loaded patch."""
    from knitfem.knit.pattern import Jersey
    from knitfem.cli.scenes import pulled

    full, _, ind = indicator(jersey(6, 6))
    eta, dist = ind(full.rest_state())
    # round-off of stiff, light yarns: EA ε_mach / (ρ h) ≈ 1e-6 m/s²
    assert eta.max() < 1e-5 * 9.81 and dist.max() < 1e-10
    fab = pulled(Jersey(6, 6), (4, 4), (0.0, 0.0, 1e-3))
    fab.fixed = (np.zeros(0, int), np.zeros(0))
    full, _, ind = indicator(fab)
    eta, _ = ind(full.rest_state())
    assert np.unravel_index(np.argmax(eta), eta.shape) == (1, 1)
    assert eta.max() > 10 * np.median(eta)


@pytest.mark.parametrize("patches", [[[True, False], [False, False]],
                                     [[True, True], [True, False]]])
def test_transfer_keeps_momentum(patches):
    """Refine and coarsen a free fabric in motion: linear momentum 1ᵀMε̇ is
    kept to round-off (contacts are internal), and the transferred state
    satisfies the new constraints."""
    from knitfem.lod.adapt import transfer

    fab = jersey(6, 6)
    full, red = models(COMM, fab, lod=LOD)
    w = VolumeWeights(fab, red.embedding.volume)
    start = mixed(full, red, w.patch_mask(np.array([[False, True], [False, False]])))
    x, v = start.rest_state(), start.rest_state()
    rng = np.random.default_rng(3)
    x.getArray()[:] += 1e-2 * fab.radius * rng.standard_normal(x.getLocalSize())
    v.getArray()[:] = 0.1 + 0.01 * rng.standard_normal(v.getLocalSize())
    new = mixed(full, red, w.patch_mask(np.array(patches)))
    x2, v2 = transfer(start, new, x, v)
    # Γ_mix may have a null space: its projection detects null pivots
    assert new._proj.getPC().getFactorMatrix().getMumpsIcntl(24) == 1

    def momentum(system, vel):
        ev, Mv = system.full_state(vel), full.M.createVecLeft()
        full.M.mult(ev, Mv)
        return COMM.tompi4py().allreduce(Mv.getArray().reshape(-1, 3).sum(0))

    p0, p1 = momentum(start, v), momentum(new, v2)
    assert np.abs(p0).min() > 1e-3 * full.total_mass
    assert np.allclose(p1, p0, rtol=3e-14, atol=0)  # measured 3e-15
    r, rv = new.C.createVecLeft(), new.C.createVecLeft()
    new.constraint_residual(x2, r)
    new.constraint_jacobian(x2).mult(v2, rv)
    # measured 7.9e-15 r and 6.1e-15 of 0.1 m/s; on 2 ranks up to 1.8e-14 r
    # and 8.7e-15 of 0.1 m/s over five runs
    assert r.norm(PETSc.NormType.INFINITY) < 1e-13 * fab.radius
    assert rv.norm(PETSc.NormType.INFINITY) < 1e-13 * 0.1


# -- the command line ------------------------------------------------------------
def knitfem_run(*args):
    import os
    import subprocess
    import sys

    env = dict(os.environ, PYTHONPATH=os.path.dirname(os.path.dirname(__file__)))
    return subprocess.run([sys.executable, "-m", "knitfem.cli", "run", *args,
                           "-skip_petscrc"], capture_output=True, text=True,
                          env=env, timeout=300)


serial_only = pytest.mark.skipif(COMM.size > 1, reason="runs knitfem in subprocesses")


@serial_only
@pytest.mark.parametrize("sampling", ["exact", "sampled"])
def test_adaptive_run_writes_indicator(tmp_path, sampling):
    """knitfem run -knit_scene pulled -knit_model mixed -knit_adapt: the pulled
    patch is refined at the start, logged, and the indicator is in
    summary.json and indicator.png (the volume part exact, and sampled: each
    new split sampled again)."""
    import json

    p = knitfem_run("-knit_scene", "pulled", "-knit_rows", "6", "-knit_cols", "9",
                    "-knit_lod", "6,5", "-knit_model", "mixed", "-knit_adapt",
                    "-knit_pull_force", "0,-1e-3,0", "-knit_t_end", "0.005",
                    "-knit_snapshots", "0.005", "-knit_sampling", sampling,
                    "-o", str(tmp_path))
    assert p.returncode == 0, p.stdout + p.stderr
    assert "adapt: t 0.0000 s, step 0: refined [[1, 0]]" in p.stdout
    rec = json.loads((tmp_path / "summary.json").read_text())
    assert rec["model"] == "mixed" and rec["adapt"]["events"][0]["refined"] == [[1, 0]]
    assert rec["adaptive"] and rec["integrator"] == "bdf2"   # its control kept
    eta = np.array(rec["indicator_last"]["eta"])
    assert eta.shape == (3, 2) and np.all(eta > 0)
    assert rec["adapt"]["unknowns_max"] == rec["unknowns"] < 3 * 6 * 75 * 0.5
    assert (tmp_path / "indicator.png").stat().st_size > 0


@serial_only
@pytest.mark.parametrize("args,message", [
    (["-knit_model", "reduced", "-knit_adapt"], "-knit_adapt needs -knit_model mixed"),
    (["-knit_model", "mixed", "-knit_full_region", "0:9,1:2"], "outside"),
    (["-knit_model", "mixed", "-knit_full_regions", "/nonexistent"], "No such file"),
    (["-knit_scene", "pulled", "-knit_pull_force", "1,2"], "3 comma-separated"),
])
def test_bad_input_is_one_line(args, message, tmp_path):
    p = knitfem_run("-knit_rows", "3", "-knit_cols", "3", "-knit_t_end", "0.01",
                    "-o", str(tmp_path), *args)
    assert p.returncode == 2, p.stdout + p.stderr
    assert message in p.stdout + p.stderr
    assert "Traceback" not in p.stderr
