"""knitfem: yarn-level knitted fabric with a mechanical level of detail, on PETSc.

Dependencies come from Debian (petsc4py, mpi4py, numpy, scipy, h5py, meshio,
matplotlib); they are not listed in install_requires so that pip never
replaces Debian's numpy, which petsc4py is built against.

The compiled yarn kernels (``knitfem/yarn/_compiled.pyx``), the yarn
contact's (``knitfem/contact/_pairs.pyx``), the bodies' distances
(``knitfem/contact/_bodies.pyx``) and the embedding's rows
(``knitfem/lod/_rows.pyx``) are built here by
Debian's Cython (``cython3``) and gcc: ``pip install -e .`` (``make setup``)
compiles them in place.
"""

from Cython.Build import cythonize
from setuptools import Extension, setup

KERNELS = Extension("knitfem.yarn._compiled", ["knitfem/yarn/_compiled.pyx"],
                    extra_compile_args=["-O3"], libraries=["blas"])
PAIRS = Extension("knitfem.contact._pairs", ["knitfem/contact/_pairs.pyx"],
                  extra_compile_args=["-O3"])
BODIES = Extension("knitfem.contact._bodies", ["knitfem/contact/_bodies.pyx"],
                   extra_compile_args=["-O3"])
ROWS = Extension("knitfem.lod._rows", ["knitfem/lod/_rows.pyx"],
                 extra_compile_args=["-O3"], libraries=["blas"])

setup(
    name="knitfem",
    version="0.1.0",
    description="Yarn-level knitted fabric simulation with mechanical level of "
    "detail, on PETSc",
    packages=["knitfem", "knitfem.knit", "knitfem.yarn", "knitfem.contact",
              "knitfem.model", "knitfem.lod", "knitfem.run", "knitfem.cli",
              "solvers", "benchmarks"],
    package_data={"solvers": ["*.rc"]},
    python_requires=">=3.9",
    ext_modules=cythonize([KERNELS, PAIRS, BODIES, ROWS], language_level=3),
    entry_points={"console_scripts": ["knitfem = knitfem.cli.main:main"]},
)
