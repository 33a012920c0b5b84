"""AIJ matrices on our own value arrays, and the storage order of any AIJ
matrix: what is written is what PETSc has, on one rank and on several."""

import numpy as np
from petsc4py import PETSc

from knitfem.model.assembly import create_aij, csr_rows
from solvers.aij import OwnAIJ, storage_pattern, storage_values

COMM = PETSc.COMM_WORLD


def random_rows(n, N, per_row=5, seed=0):
    """CSR (indptr, global columns sorted in each row) of n local rows of an
    N-column matrix, each row reaching across all ranks' columns."""
    rng = np.random.default_rng(seed + COMM.rank)
    cols = [np.sort(rng.choice(N, per_row, replace=False)) for _ in range(n)]
    indptr = np.arange(n + 1) * per_row
    return indptr, np.concatenate(cols)


def test_own_aij_holds_what_is_written_where_place_says():
    """Values written at ``place``(CSR positions) are the matrix's CSR
    values after an assembly, and again after a second write."""
    n, N = 6, 6 * COMM.size
    indptr, indices = random_rows(n, N)
    own = OwnAIJ.from_csr(COMM, ((n, N), (n, N)), indptr, indices)
    for seed in (1, 2):
        values = np.random.default_rng(seed).random(len(indices))
        own.values[own.place(np.arange(len(indices)))] = values
        own.assemble()
        ai, aj, av = own.mat.getValuesCSR()
        assert np.array_equal(ai, indptr) and np.array_equal(aj, indices)
        assert np.array_equal(av, values)
    assert np.array_equal(own.place(np.array([-1, 0])) >= 0, [False, True])
    own.mat.destroy()


def test_storage_order_of_a_petsc_matrix():
    """``storage_pattern`` and ``storage_values`` of a matrix PETSc built
    itself give every entry's row, column and value."""
    n, N = 5, 5 * COMM.size
    indptr, indices = random_rows(n, N, seed=3)
    values = np.arange(len(indices), dtype=float) + 100 * COMM.rank
    A = create_aij(COMM, (n, N), (n, N), (indptr, indices, values))
    ptr, cols, position, sizes = storage_pattern(A)
    assert np.array_equal(ptr, indptr) and np.array_equal(cols, indices)
    with storage_values(A, sizes) as parts:
        stored = np.concatenate(parts)
    assert len(parts) == min(COMM.size, 2) and sum(sizes) == len(values)
    order = np.arange(len(values)) if position is None else position
    assert np.array_equal(stored[order], values)
    if position is not None:                 # the diagonal block comes first
        start, end = A.getOwnershipRangeColumn()
        inside = (indices >= start) & (indices < end)
        assert np.all(position[inside] < sizes[0])
        assert np.all(position[~inside] >= sizes[0])
        rows = csr_rows(indptr)
        for block in (inside, ~inside):      # in CSR order within each block
            assert np.all(np.diff(position[block]) > 0)
            assert np.all(np.diff(rows[block]) >= 0)
    A.destroy()
