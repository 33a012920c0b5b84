"""The reduced model's parts, evaluated side by side on a rank's cores.

A sampled reduced model's energy, forces and tangent are sums of
independent parts over different yarn elements: the sampled elements,
the shell stretch's stitches, the contact set's elements near a body.
Each part writes only an output of its own (a number, an (n, 3) array of
forces, a ``TangentPart`` of the tangent's values), and the outputs are
added in the parts' order afterwards, so a result is the same to the bit
whether one thread formed the parts or several. Their heavy loops (the
compiled kernels, BLAS's and numpy's products) let go of Python's lock,
so a second thread overlaps them in part: on the 60×120 sleeve landed on
the arm a tangent takes 88 ms on two threads against 108 ms on one, the
forces 35 against 41 ms, and the whole bend 79 s against 94 s (run back
to back on two cores).

``-knit_threads`` chooses how many; by default, the cores this process
may run on shared among the ranks of its machine (one each under an
``mpirun`` that fills the machine: ranks, not threads, share the cores).
"""

import os
from concurrent.futures import ThreadPoolExecutor

__all__ = ["Parts", "default_threads"]


def default_threads(comm):
    """The cores this process may run on (its affinity; the machine's where
    the system keeps none) over the ranks of ``comm`` on its machine, at
    least 1 (collective)."""
    from mpi4py import MPI

    mpi = comm.tompi4py()
    local = mpi.Split_type(MPI.COMM_TYPE_SHARED)
    ranks = local.Get_size()
    local.Free()
    cores = (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
             else os.cpu_count() or 1)
    return max(1, cores // ranks)


class Parts:
    """Run independent jobs on ``threads`` threads (one after the other on
    one): ``map(jobs)`` gives their results in the jobs' order."""

    def __init__(self, threads=1):
        self.threads = max(1, int(threads))
        self.pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None

    def map(self, jobs):
        """The results of the callables ``jobs``, in order."""
        if self.pool is None or len(jobs) < 2:
            return [job() for job in jobs]
        done = [self.pool.submit(job) for job in jobs[1:]]
        first = jobs[0]()
        return [first] + [f.result() for f in done]

    def close(self):
        if self.pool is not None:
            self.pool.shutdown()
            self.pool = None
