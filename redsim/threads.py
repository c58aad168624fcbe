"""Run a block of torch work on a set number of intra-op threads, then give the caller back its own setting.

redsim's latent steps are many small tensor ops, which torch's intra-op threads do not speed up: on a 2-core machine
a Chain-v0 step took 15 ms on one thread and 73-78 ms on torch's default two while another process kept one core
busy (docs/env-speed.md, "Stop 38: threads"). An env therefore computes on its own ``threads`` (default 1) inside
:func:`torch_threads`, and the caller's code (a policy network, a training loop) keeps the setting it chose.

``torch.set_num_threads`` is process-wide. Blocks may nest (the innermost count holds until it ends) and may run in
several Python threads at once: the caller's setting is saved when the first block starts and restored when the last
one ends, so it is never lost.
"""

from __future__ import annotations

import contextlib
import numbers
import threading
from collections.abc import Iterator

import torch

_lock = threading.Lock()
_counts: list[int] = []  # the counts of the blocks running now, innermost last
_saved = 0  # the caller's setting while any block runs


def check_threads(threads: int | None) -> int | None:
    """``threads`` as an int >= 1, or None (leave torch's setting as it is).

    Raises:
        ValueError: anything else (a bool, a float, a count < 1).
    """
    if threads is None:
        return None
    if isinstance(threads, bool) or not isinstance(threads, numbers.Integral) or threads < 1:
        raise ValueError(f"threads must be None or an integer >= 1, got {threads!r}")
    return int(threads)


@contextlib.contextmanager
def torch_threads(threads: int | None) -> Iterator[None]:
    """Run the block on ``threads`` torch intra-op threads (None: as the caller set them), restoring the caller's
    setting after it (module doc)."""
    global _saved
    if threads is None:
        yield
        return
    with _lock:
        if not _counts:
            _saved = torch.get_num_threads()
        _counts.append(threads)
        if torch.get_num_threads() != threads:
            torch.set_num_threads(threads)
    try:
        yield
    finally:
        with _lock:
            _counts.pop()
            wanted = _counts[-1] if _counts else _saved
            if torch.get_num_threads() != wanted:
                torch.set_num_threads(wanted)


__all__ = ["check_threads", "torch_threads"]
