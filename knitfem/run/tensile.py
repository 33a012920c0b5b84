"""A relaxed knit stretched quasi-statically: force against strain.

A textile's tensile test clamps a swatch at two opposite edges and pulls
one clamp away from the other, slowly, recording the force. Here the clamps
are the loop heads: along the wales, the heads of the first and the last
course; along the courses, the heads of the first and the last stitch of
every course. Each clamp holds its heads where the relaxed knit has them
(``Fabric.fixed``: P_f(s) = x₀, all three components), so at zero strain the
relaxed knit is in equilibrium and the clamps pull nothing. The moving
clamp is then carried along e, the unit vector from the fixed clamp's
centroid to its own, by ε L (L the distance between the centroids, ε the
nominal strain), and the knit is brought to its constrained energy minimum
at each strain in turn (``solvers.statics_descent``, no gravity, yarn
contact as the relaxation had it).

The force comes from the energy: with Π(ε) the knit's energy at the
minimum, the clamp's pull along e is F = dΠ/d(εL), taken between
consecutive strains as

    F(ε_{k+½}) = (Π(ε_{k+1}) − Π(ε_k)) / (L (ε_{k+1} − ε_k)),

exact for a conservative quasi-static path. The clamps' multipliers give
the same force at each strain: a hold g_i = P_f(s_i) − x_i (B-spline
weights summing to one) pulls the knit with −μ_i, and the moving clamp's
pull along e is R(ε) = −Σ_i μ_i·e over its heads, and the energy stored
between two strains is its work, Π(ε₂) − Π(ε₀) = ∫ R L dε (the tests check
it by Simpson's rule).
The initial tensile stiffness is the secant F / ε at the
first strain's midpoint, in newtons, and per unit width of the clamped
edge (N/m: a fabric's tensile modulus per unit width).
"""

import numpy as np

__all__ = ["stretch", "DIRECTIONS"]

DIRECTIONS = ("wales", "courses")


def clamps(jersey, along):
    """(yarn, s, moving) of the loop heads a stretch ``along`` the wales or
    the courses holds: ``moving`` marks the heads of the clamp that moves."""
    heads = jersey.heads(0)
    rows, cols = jersey.rows, jersey.cols
    if along == "wales":
        yarn = np.repeat([0, rows - 1], cols)
        s = np.tile(heads, 2)
    elif along == "courses":
        yarn = np.tile(np.arange(rows), 2)
        s = np.repeat([heads[0], heads[-1]], rows)
    else:
        raise ValueError(f"stretch along {along!r}: use one of {', '.join(DIRECTIONS)}")
    return yarn, s, np.arange(len(yarn)) >= len(yarn) // 2


def stretch(comm, jersey, along, strains, accel=1e-4):
    """Stretch the relaxed knit ``jersey.rest`` along its wales or courses
    through the nominal ``strains`` (increasing, > 0), serially. Returns a
    dict: ``length_m`` L, ``width_m`` (the clamped edge's length),
    ``strain`` and ``energy_J`` (ε = 0 first), ``force_N`` and
    ``force_strain`` (the midpoints), ``reaction_N`` R at every strain
    (``strain``), ``stiffness_N`` (F / ε at the first
    midpoint), ``stiffness_N_per_m`` (over the width) and ``newton``
    (iterations a strain)."""
    from knitfem.knit.pattern import jersey_fabric
    from knitfem.model.full import FullModel, Material
    from solvers.statics_descent import ConstrainedDescent

    if jersey.rest is None:
        raise ValueError("stretch a relaxed knit: give the jersey its rest "
                         "(run.relax.RelaxedKnit)")
    if comm.getSize() != 1:
        raise ValueError("the tensile test runs on one rank")
    strains = np.asarray(strains, dtype=float)
    if len(strains) < 1 or np.any(np.diff(np.r_[0.0, strains]) <= 0):
        raise ValueError("strains: increasing and positive, e.g. 0.005,0.01,0.02")
    fabric = jersey_fabric(jersey)
    yarn, s, moving = clamps(jersey, along)
    fabric.fixed = (yarn, s)
    system = FullModel(comm, fabric, Material(gravity=0.0),
                       yarn_contact=jersey.rest.yarn_contact)
    held = system.constraints.rhs
    x0 = held.copy()
    e = x0[moving].mean(axis=0) - x0[~moving].mean(axis=0)
    L = float(np.linalg.norm(e))
    e /= L
    fixed_edge = x0[~moving]
    width = float(np.sum(np.linalg.norm(np.diff(fixed_edge, axis=0), axis=1)))
    solver = ConstrainedDescent(system)
    x = system.start_state()
    energy, newton, reaction = [system.elastic_energy(x)], [], [0.0]
    rows = system.constraints.hold_rows[moving][:, None] + np.arange(3)
    try:
        for eps in strains:
            held[moving] = x0[moving] + eps * L * e
            newton.append(solver.minimize(x, accel))
            energy.append(system.elastic_energy(x))
            mu = solver.mu.getArray(readonly=True)
            reaction.append(float(-np.sum(mu[rows] @ e)))
    finally:
        x.destroy()
        solver.destroy()
        system.destroy()
    strain = np.r_[0.0, strains]
    force = np.diff(energy) / (L * np.diff(strain))
    mid = 0.5 * (strain[1:] + strain[:-1])
    return dict(along=along, length_m=L, width_m=width, strain=strain.tolist(),
                energy_J=[float(v) for v in energy], force_strain=mid.tolist(),
                force_N=force.tolist(), reaction_N=reaction, stiffness_N=float(force[0] / mid[0]),
                stiffness_N_per_m=float(force[0] / mid[0] / width), newton=newton)
