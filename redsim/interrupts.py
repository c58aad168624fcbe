"""Ctrl-C between the steps of a loop, not inside one.

A KeyboardInterrupt raised in the middle of a training step (between the optimizer's update and the line that counts
the step, or between two parameter groups of the update) leaves a state whose weights and step count disagree, and
a resume from it is no longer the run it continues. :func:`deferred_interrupts` holds Ctrl-C (and a SIGTERM that
someone has made raise, as the ``redsim`` command line does; an ignored signal stays ignored) until the loop calls
its check at a step boundary; a second signal raises :class:`ForcedInterrupt` at once, for a step that never ends.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator
from types import FrameType


class ForcedInterrupt(KeyboardInterrupt):
    """A second signal while the first waited for the step's end: raised inside the step, whose state is partial."""


@contextlib.contextmanager
def deferred_interrupts(*, forced: bool = True) -> Iterator[Callable[[], None]]:
    """Within the block, SIGINT (and SIGTERM where a Python handler is set for it) only records the signal; the
    yielded ``check()`` then calls the handler the block replaced (Python's raises KeyboardInterrupt; a caller's own
    does what it does), at a step boundary. A second signal before that raises :class:`ForcedInterrupt` at once;
    with ``forced=False`` it waits too, for a block that always ends soon and must not be stopped inside (importing
    torch: an exception raised in its C++ start-up aborts the process). Off the main thread (where signals cannot be
    handled) ``check`` does nothing and signals keep their handlers."""
    if threading.current_thread() is not threading.main_thread():
        yield lambda: None
        return
    pending: list[int] = []

    def record(signum: int, frame: FrameType | None) -> None:
        if pending and forced:  # the second one: the step is not ending, stop now
            raise ForcedInterrupt(f"signal {signum}")
        pending.append(signum)

    wanted = [s for s in (signal.SIGINT, signal.SIGTERM) if callable(signal.getsignal(s))]  # not ignored or default
    previous = {signum: signal.signal(signum, record) for signum in wanted}

    def check() -> None:
        while pending:
            signum = pending.pop(0)
            previous[signum](signum, None)

    try:
        yield check
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    check()  # a signal after the block's last check (and no exception on its way out): not lost
