"""One BLAS thread for the small dense problems of calibration and diagnosis: threads there only contend.

`threadpoolctl.threadpool_limits` finds the process's thread pools afresh at every call by walking every loaded
shared library (14 ms here, 30 ms on a loaded machine), and a diagnosis calls it for every calibration. The pools
are found once instead, and again only when modules were imported since (a library loaded later, such as
scikit-learn's OpenMP, is then limited too).
"""

from __future__ import annotations

import sys
from contextlib import AbstractContextManager

from threadpoolctl import ThreadpoolController

_found: tuple[int, ThreadpoolController] | None = None


def one_blas_thread() -> AbstractContextManager:
    """A context in which BLAS and OpenMP run on one thread (restored on leaving)."""
    global _found
    if _found is None or _found[0] != len(sys.modules):
        _found = (len(sys.modules), ThreadpoolController())
    return _found[1].limit(limits=1)
