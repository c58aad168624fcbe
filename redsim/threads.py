"""Run a block of torch work on a set number of intra-op threads, then give the caller back its own setting.

redsim's latent steps are many small tensor ops, which torch's intra-op threads do not speed up: on a 2-core machine
a Chain-v0 step took 14 ms on one thread and 84 ms on torch's default two while another process kept one core busy
(docs/env-speed.md, "Stop 38: threads"). An env therefore computes on its own ``threads`` (default 1) inside
:func:`torch_threads`, and the caller's code (a policy network, a training loop) keeps the setting it chose.

Each block saves the setting it found and restores it when it ends (also when it raises), so blocks nest. torch's
setting belongs to the Python thread that makes it (an OpenMP setting of the calling thread), so blocks in several
Python threads do not disturb each other's.
"""

from __future__ import annotations

import contextlib
import numbers
from collections.abc import Iterator

import torch

MAX_THREADS = 2**15
"""The most threads :func:`check_threads` accepts (torch refuses counts past a C int; none is useful)."""


def check_threads(threads: int | None) -> int | None:
    """``threads`` as an int in [1, :data:`MAX_THREADS`], or None (leave torch's setting as it is).

    Raises:
        ValueError: anything else (a bool, a float, a count out of range).
    """
    if threads is None:
        return None
    if isinstance(threads, bool) or not isinstance(threads, numbers.Integral) or not 1 <= threads <= MAX_THREADS:
        raise ValueError(f"threads must be None or an integer in [1, {MAX_THREADS}], got {threads!r}")
    return int(threads)


@contextlib.contextmanager
def torch_threads(threads: int | None) -> Iterator[None]:
    """Run the block on ``threads`` torch intra-op threads (None: as the caller set them), restoring the setting it
    found after it (module doc)."""
    before = torch.get_num_threads()
    if threads is None or threads == before:
        yield
        return
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


__all__ = ["MAX_THREADS", "check_threads", "torch_threads"]
