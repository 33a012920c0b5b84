"""The full (yarn-level) model assembled into PETSc objects: the layout of
the yarns over ranks, the mass M = m ⊗ I₃, forces, tangent and constraints."""
