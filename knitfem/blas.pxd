# BLAS's dgemm as the compiled kernels call it (linked with -lblas: Debian's
# OpenBLAS where it is installed), cimported by knitfem/yarn/_compiled.pyx
# and knitfem/lod/_rows.pyx.

cdef extern from *:
    """
    void dgemm_(const char *, const char *, const int *, const int *,
                const int *, const double *, const double *, const int *,
                const double *, const int *, const double *, double *,
                const int *);
    """
    void dgemm_(const char *transa, const char *transb, const int *m,
                const int *n, const int *k, const double *alpha, const double *a,
                const int *lda, const double *b, const int *ldb,
                const double *beta, double *c, const int *ldc) nogil
