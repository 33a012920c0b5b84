"""What holds yarns together and apart: the persistent crossings, fixed or
sliding (constraints C(ε) = 0 and their PETSc assembly), and the rigid bodies
with their barrier and friction."""
