"""One BLAS thread per process.

The project parallelises with processes, one per core: the Blender workers, the navigation and landmark
workers, the horizon maps computed ahead, the training-data builders. A BLAS that starts its own threads in
each of them fights those processes for the same cores, and it changes the rendered bytes:

- Speed. Measured on the 2-core development machine with both cores busy, numpy's OpenBLAS (0.3.23,
  pthreads) took 2.9 ms for the inverse of a 3 x 3 matrix (9 us on one thread) and 8.5 ms for a
  (512^2 x 3) @ (3,) product (0.46 ms on one thread): the shapes of the rim ellipse projection and of the
  fast renderer's shading. The project has no BLAS call large enough for a second thread to pay.
- Bytes. OpenBLAS splits a large product between its threads, and some elements round differently: a
  navigation frame's I/F differed in 1518 of 262,144 pixels (by <= 1.1e-8) between one and two BLAS
  threads. The default is one thread per core, so the same render would give other bytes on a node with
  another core count.

OpenBLAS reads the variable once, when the library loads (numpy's or scipy's import), so
:func:`one_blas_thread` runs before either is imported: first thing in ``crater_synth`` (the host, and every
process it forks; a value the user set is kept there) and in the Blender worker (always one thread: its
bytes are the dataset's); subprocesses inherit the environment. torch has its own thread pool
(``torch.set_num_threads``; the trainers set it) and is not affected.
"""

from __future__ import annotations

import os

# OpenBLAS: numpy's and scipy's BLAS in the pinned wheels (the variable every OpenBLAS build reads).
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS",)


def one_blas_thread(force: bool = False) -> None:
    """Set each of :data:`BLAS_THREAD_VARIABLES` to 1: where the environment does not set it already, or
    always with ``force``."""
    for name in BLAS_THREAD_VARIABLES:
        if force:
            os.environ[name] = "1"
        else:
            os.environ.setdefault(name, "1")
