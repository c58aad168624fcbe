"""A process forked from one that imported redsim runs torch on one intra-op thread.

torch's CPU wheels run intra-op parallel regions on GNU OpenMP, whose thread pool does not survive
``fork``: a forked child that enters a parallel region after its parent has used one waits forever
for threads that were not copied. Gymnasium's ``AsyncVectorEnv`` forks its workers by default on
Linux (after building one env in the parent to read its spaces), so
``gym.make_vec("RedSim/...", vectorization_mode="async")`` hung before this module existed. Registered at
import: the child starts on one thread (as torch's own ``DataLoader`` workers do); it may raise the
count itself if its parent never ran a parallel region. Spawned processes are not affected. Importing this module
does not import torch, and a child of a parent that never loaded torch is left alone: it has no pool to lose, and it
imports torch with torch's default thread count (an env still computes on its own ``threads``, default 1).
"""

from __future__ import annotations

import os
import sys


def one_thread_in_child() -> None:
    """``os.register_at_fork`` handler: one torch intra-op thread in the forked child.

    Nothing to do where the parent never imported torch (no thread pool to lose); importing it here would cost
    every forked child ~2 s.
    """
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(1)


if hasattr(os, "register_at_fork"):  # POSIX only; Windows has no fork
    os.register_at_fork(after_in_child=one_thread_in_child)

__all__ = ["one_thread_in_child"]
