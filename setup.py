"""knitfem: yarn-level knitted fabric with a mechanical level of detail, on PETSc.

Dependencies come from Debian (petsc4py, mpi4py, numpy, scipy, h5py, meshio,
matplotlib); they are not listed in install_requires so that pip never
replaces Debian's numpy, which petsc4py is built against.
"""

from setuptools import setup

setup(
    name="knitfem",
    version="0.1.0",
    description="Yarn-level knitted fabric simulation with mechanical level of "
    "detail, on PETSc",
    packages=["knitfem", "solvers", "benchmarks"],
    package_data={"solvers": ["*.rc"]},
    python_requires=">=3.9",
    entry_points={"console_scripts": ["knitfem = knitfem.cli:main"]},
)
