"""Yarn kernels behind one switch: compiled loops (default) or the numpy reference.

``-knit_kernels compiled`` runs the loops over elements × quadrature points of
``knitfem/yarn/_compiled.pyx`` (Cython, built by ``pip install -e .``, i.e. ``make
setup``); ``-knit_kernels numpy`` runs the vectorised reference of
``knitfem.yarn.elements``. Both compute, for the elements of a ``YarnElements``,

    add_gradient(x, out, scale)          out += scale · ∂E/∂p            (ncp, 3)
    hessian_values(x, slot, values, xref)  values = Σ_e K_e, K_e[m, n] added at
                                         values[slot[e, m, n]]  (CSR values)
    element_gradient(x), element_hessian(x, xref)   (ne, 12), (ne, 12, 12)

with E = E_s + E_b (``xref``, optional: the axial force of the Newton matrix
linearised from the state xref, ``yarn.stretch_terms``), and the same mathematics (``knitfem.yarn.elements``'s docstring);
the tests hold them equal to 1e-12 relative. x is (ncp, 3), C-contiguous
(a view of a PETSc Vec's array will do).
"""

import importlib

import numpy as np

from knitfem.errors import KnitError

__all__ = ["KINDS", "yarn_kernels", "compiled_module"]

KINDS = ("compiled", "numpy")
VERSION = 5                 # of knitfem/yarn/_compiled.pyx, which this module calls


def compiled_module(name="knitfem.yarn._compiled", version=VERSION):
    """The compiled extension ``name`` (by default the yarn kernels) of its
    source's ``version``, or a KnitError saying how to build it (not built,
    or built from an older source)."""
    try:
        module = importlib.import_module(name)
    except ImportError as err:
        raise KnitError(f"the compiled kernels are not built ({err}): run `make "
                        "setup` (or `pip install -e .`), or use -knit_kernels "
                        "numpy") from None
    if getattr(module, "VERSION", None) != version:
        raise KnitError("the compiled kernels were built from an older "
                        f"{name.replace('.', '/')}.pyx: run `make setup` (or `pip "
                        "install -e .`), or use -knit_kernels numpy")
    return module


class NumpyKernels:
    """The vectorised reference of ``YarnElements`` (numpy, bincount)."""

    kind = "numpy"

    def __init__(self, elements):
        self.elements = elements

    def add_gradient(self, x, out, scale=1.0):
        out += scale * self.elements.gradient(x)

    def hessian_values(self, x, slot, values, xref=None):
        H = self.elements.element_hessian(x, xref)
        values[:] = np.bincount(slot.ravel(), weights=H.ravel(), minlength=len(values))

    def element_gradient(self, x):
        return self.elements.element_gradient(x)

    def element_hessian(self, x, xref=None):
        return self.elements.element_hessian(x, xref)


class CompiledKernels:
    """The loops of ``knitfem.yarn._compiled`` on the arrays of a ``YarnElements``."""

    kind = "compiled"

    def __init__(self, elements):
        el = elements
        self.module = compiled_module()
        self.ne = el.ne
        self.args = (np.ascontiguousarray(el.conn, dtype=np.int64),
                     np.ascontiguousarray(el.D), np.ascontiguousarray(el.Xp2),
                     np.ascontiguousarray(el.W), np.ascontiguousarray(el.kappa0),
                     el.EA, el.EI, el.delta)
        self.blocks = {}             # id(slot) → (slot, its block_slots)

    def add_gradient(self, x, out, scale=1.0):
        self.module.add_gradient(np.ascontiguousarray(x), *self.args, scale, out)

    def hessian_values(self, x, slot, values, xref=None):
        known = self.blocks.get(id(slot))
        if known is None or known[0] is not slot:
            known = self.blocks[id(slot)] = (slot, block_slots(slot))
        self.module.hessian_values(np.ascontiguousarray(x), *self.args, *known[1],
                                   values, _contiguous(xref))

    def element_gradient(self, x):
        out = np.empty((self.ne, 12))
        self.module.element_gradients(np.ascontiguousarray(x), *self.args, out)
        return out

    def element_hessian(self, x, xref=None):
        out = np.empty((self.ne, 12, 12))
        self.module.element_hessians(np.ascontiguousarray(x), *self.args, out,
                                     _contiguous(xref))
        return out


def _contiguous(x):
    return None if x is None else np.ascontiguousarray(x)


def block_slots(slot):
    """(block, stride) of element slots (ne, 12, 12) made of 3 × 3 blocks laid
    out as rows ``stride`` apart: slot[e, 3a + i, 3b + j] = block[e, a, b] +
    stride[e, a] i + j (as ``ElementPattern.blocks3`` gives them)."""
    s = slot.reshape(-1, 4, 3, 4, 3)
    block = np.ascontiguousarray(s[:, :, 0, :, 0], dtype=np.int64)
    stride = np.ascontiguousarray(s[:, :, 1, 0, 0] - s[:, :, 0, 0, 0], dtype=np.int64)
    i, j = np.arange(3)[:, None], np.arange(3)
    expect = (block[:, :, None, :, None] + stride[:, :, None, None, None]
              * i[None, None, :, None, :] + j[None, None, None, None, :])
    if not np.array_equal(s, expect):
        raise ValueError("element slots are not made of 3 x 3 blocks with "
                         "unit-stride rows")
    return block, stride


def yarn_kernels(elements, kind="compiled"):
    """The kernels of ``kind`` (one of ``KINDS``) for ``elements``."""
    if kind not in KINDS:
        raise KnitError(f"kernels {kind!r}: expected one of {', '.join(KINDS)}")
    return (CompiledKernels if kind == "compiled" else NumpyKernels)(elements)
