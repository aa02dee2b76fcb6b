"""
numpy's BLAS on one thread: the solver's matrices are 4x4 to 12x12.

A second BLAS thread only fights the first (and a node's executor) for the cores: on this
project's 2-core machine under load the refinement took 91 ms of CPU with the default threads
against 20 ms with one.  The thread count is read by the BLAS library when numpy loads it,
so the entry points call `single_threaded_blas` before anything imports numpy.  Standard
library only.
"""

import os

SINGLE_THREADED_BLAS = {'OPENBLAS_NUM_THREADS': '1', 'OMP_NUM_THREADS': '1',
                        'MKL_NUM_THREADS': '1'}


def single_threaded_blas():
    """Run numpy's BLAS on one thread, unless the user set the thread count."""
    for name, value in SINGLE_THREADED_BLAS.items():
        os.environ.setdefault(name, value)
