"""One budget of threads for a run: torch's pool and the BLAS and OpenMP pools numpy and scipy load.

``torch.set_num_threads`` sizes torch's pool only. numpy's and scipy's OpenBLAS start a thread per core when
they load, and a simulator built on them (controlgym's) then runs on every core: two runs side by side on two
cores each took both. :func:`pin_threads` sizes every pool loaded so far (threadpoolctl); a study's child
processes also start with the pools' environment variables set (:func:`pimbrl.experiments.runner.pinned_environment`),
which covers libraries loaded later.
"""

from __future__ import annotations

import torch
from threadpoolctl import threadpool_limits

__all__ = ["pin_threads"]


def pin_threads(threads: int) -> None:
    """Size torch's pool and every BLAS and OpenMP pool this process has loaded to ``threads``."""
    torch.set_num_threads(threads)
    threadpool_limits(limits=threads)
