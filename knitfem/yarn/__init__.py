"""The yarn as a 1-D element: uniform cubic B-splines, the elements' mass,
stretching and bending energies, and their compiled kernels beside the numpy
reference."""
