"""PETSc matrices from numpy CSR arrays: layouts, patterns, one-call assembly.

Yarn matrices are assembled without a Python loop over entries: the sparsity
of a set of 4-point elements is found once (``ElementPattern``), every
element entry gets its position in the CSR value array, and values are
summed into place with ``np.bincount``. The 3-D forms follow from the scalar
pattern: M = m ⊗ I₃ (``kron_identity``) and a full 3×3 block pattern for the
tangent stiffness (``ElementPattern.blocks3``). Coordinates are interleaved,
dof = 3 · control point + component, and PETSc block size is 3.
"""

import numpy as np
from petsc4py import PETSc

__all__ = ["YarnLayout", "ElementPattern", "kron_identity", "create_aij",
           "csr_rows"]


class YarnLayout:
    """Whole yarns per rank, in order; the rank's control points are contiguous.

    Collective only in spirit: every rank computes the same split of the
    yarns whose control points start at ``yarn_start`` (nyarn + 1 offsets)
    over ``comm.size``: rank r's first yarn is the one whose first control
    point lies nearest r · N / size (halves up), so that ranks hold about as
    many control points each (yarns of one length: counts that differ by at
    most one).
    """

    def __init__(self, comm, yarn_start):
        self.comm = comm
        self.yarn_offset = np.asarray(yarn_start, dtype=np.int64)
        self.nyarn = len(self.yarn_offset) - 1
        self.ncp = int(self.yarn_offset[-1])
        target = np.arange(comm.size + 1) * self.ncp / comm.size
        near = np.searchsorted(self.yarn_offset, target)          # first at or above
        below = np.maximum(near - 1, 0)
        closer = target - self.yarn_offset[below] < self.yarn_offset[near] - target
        self.yarn_ranges = np.where(closer, below, near)
        self.yarn_ranges[[0, -1]] = 0, self.nyarn
        self.yarn_start = int(self.yarn_ranges[comm.rank])
        self.yarn_end = int(self.yarn_ranges[comm.rank + 1])
        self.cp_ranges = self.yarn_offset[self.yarn_ranges]
        self.cp_start = int(self.cp_ranges[comm.rank])
        self.cp_end = int(self.cp_ranges[comm.rank + 1])

    @property
    def local_yarns(self):
        return range(self.yarn_start, self.yarn_end)

    @property
    def ncp_local(self):
        return self.cp_end - self.cp_start

def csr_rows(indptr):
    """Row index of every CSR entry (PETSc's integer type)."""
    return np.repeat(np.arange(len(indptr) - 1, dtype=PETSc.IntType), np.diff(indptr))


def csr_positions(indptr, first):
    """Where every entry of a CSR pattern goes when its row i starts at
    ``first``[i] of another: first[i] + (k − indptr[i]) for entry k of row i."""
    return np.repeat(first - indptr[:-1], np.diff(indptr)) + np.arange(indptr[-1])


class ElementPattern:
    """Scalar CSR pattern of elements and the slot of each element entry.

    An element is a set of control points that it couples all to all: a
    yarn segment (4 points) or a contact (8 points, 4 on each yarn).

    Parameters
    ----------
    conns : (ne, k) int array, or a list of them (sets of elements)
        Global control-point indices of each element.
    row_start, nrows : int
        The local rows [row_start, row_start + nrows); entries in other rows
        are left out and get slot −1.

    ``slots`` holds each set's (ne, k, k) slots, ``slot`` the first set's.
    """

    def __init__(self, conns, row_start, nrows):
        conns = [conns] if isinstance(conns, np.ndarray) else list(conns)
        self.conn, self.row_start, self.nrows = conns[0], row_start, nrows
        self.conns = conns
        ncols = max([int(c.max()) + 1 for c in conns if c.size] + [1])
        keys, local = [], []
        for conn in conns:
            ne, k = conn.shape
            rows = np.broadcast_to(conn[:, :, None], (ne, k, k)) - row_start
            cols = np.broadcast_to(conn[:, None, :], (ne, k, k))
            local.append((rows >= 0) & (rows < nrows))
            keys.append((rows.astype(np.int64) * ncols + cols)[local[-1]])
        keys, inverse = np.unique(np.concatenate(keys), return_inverse=True)
        r, self.indices = np.divmod(keys, ncols)
        self.indptr = np.searchsorted(r, np.arange(nrows + 1)).astype(np.int64)
        self.slots, start = [], 0
        for mask in local:
            slot = np.full(mask.shape, -1, dtype=np.int64)
            slot[mask] = inverse[start:start + mask.sum()]
            start += mask.sum()
            self.slots.append(slot)
        self.slot = self.slots[0]

    def assemble(self, elements):
        """CSR values Σ_e over (ne, 4, 4) element matrices."""
        return np.bincount(self.slot.ravel(), weights=elements.ravel(),
                           minlength=len(self.indices))

    def blocks3(self, diagonal=()):
        """Pattern of the interleaved 3-D matrix with full 3×3 blocks.

        Returns (indptr3, indices3, slot3s) with slot3s[i] (ne, 3k, 3k) the
        value position of entry (3a + p, 3b + q) of an element of set i (−1
        where the row is not local); for the sets i in ``diagonal``, whose
        entries are blocks h ⊗ I₃ (the contacts' curvature), slot3s[i] is
        (ne, 3, k, k): the position of entry (3a + d, 3b + d) at [e, d, a, b].
        """
        length = np.diff(self.indptr)
        k = np.arange(len(self.indices)) - np.repeat(self.indptr[:-1], length)
        comp = np.arange(3)
        # row 3I + i starts at 9·indptr[I] + 3·i·len(I); entry (I,J) is the k-th
        # of row I, and column 3J + j sits 3k + j further on.
        row_len3 = np.repeat(3 * length, 3)
        indptr3 = np.concatenate([[0], np.cumsum(row_len3)]).astype(np.int64)
        base = (9 * np.repeat(self.indptr[:-1], length))[:, None, None] \
            + 3 * comp[None, :, None] * np.repeat(length, length)[:, None, None] \
            + 3 * k[:, None, None] + comp[None, None, :]
        indices3 = np.empty(indptr3[-1], dtype=np.int64)
        indices3[base.ravel()] = np.broadcast_to(
            3 * self.indices[:, None, None] + comp[None, None, :], base.shape).ravel()
        slot3s = []
        for i, slot in enumerate(self.slots):
            ne, n = slot.shape[:2]
            if i in diagonal:
                s3 = np.where(slot[..., None] >= 0, base[:, comp, comp][slot], -1)
                slot3s.append(np.ascontiguousarray(s3.transpose(0, 3, 1, 2)))
                continue
            s3 = np.where(slot[..., None, None] >= 0, base[slot], -1)  # (ne,n,n,3,3)
            slot3s.append(s3.transpose(0, 1, 3, 2, 4).reshape(ne, 3 * n, 3 * n))
        return indptr3, indices3, slot3s


def kron_identity(indptr, indices, values):
    """CSR of A ⊗ I₃ from the CSR of a scalar A (rows 3I + i, columns 3J + i)."""
    length = np.diff(indptr)
    rows = csr_rows(indptr)
    comp = np.arange(3)
    indptr3 = np.concatenate([[0], np.cumsum(np.repeat(length, 3))]).astype(np.int64)
    # row 3I + i holds the entries of row I, at columns 3J + i.
    pos = np.repeat(indptr[:-1], length)
    k = np.arange(len(indices)) - pos
    slot = 3 * pos[:, None] + comp[None, :] * length[rows][:, None] + k[:, None]
    indices3 = np.empty(3 * len(indices), dtype=np.int64)
    values3 = np.empty(3 * len(indices))
    indices3[slot] = 3 * indices[:, None] + comp
    values3[slot] = values[:, None]
    return indptr3, indices3, values3


def create_aij(comm, rows, cols, csr, bsize=None):
    """A PETSc AIJ matrix, exactly preallocated and filled from CSR in one call.

    Collective. ``rows``/``cols`` are (local, global) sizes; ``csr`` =
    (indptr, global column indices, values) of the local rows.
    """
    indptr, indices, values = csr
    A = PETSc.Mat().createAIJ(
        size=(rows, cols), bsize=bsize,
        csr=(np.asarray(indptr, dtype=PETSc.IntType),
             np.asarray(indices, dtype=PETSc.IntType),
             np.asarray(values, dtype=PETSc.ScalarType)),
        comm=comm)
    A.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
    A.assemble()
    return A
