"""The one worker-pool helper: processes started by a fork server, never forked from a threaded parent.

Forking a process whose OpenCV / BLAS thread pools are running can deadlock
the child (seen: a synth worker hanging in ``cv2.setNumThreads``), so pools
use the ``forkserver`` start method (``spawn`` where it is missing). As with
any non-fork pool, a script that calls the pipeline at top level needs the
usual ``if __name__ == "__main__":`` guard.
"""
from __future__ import annotations

import multiprocessing as mp
from concurrent.futures import ProcessPoolExecutor


def process_pool(workers: int) -> ProcessPoolExecutor:
    """Returns a ProcessPoolExecutor of ``workers`` processes started safely (forkserver or spawn)."""
    method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
    return ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context(method))
