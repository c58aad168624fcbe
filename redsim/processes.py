"""Run a function in a fresh spawned process and get its result or its exception back: where a benchmark's step needs
its own process (its peak memory its own) and must not wait forever for one the kernel killed, as a
``multiprocessing.Pool`` does. Importing it does not import torch.

The process's Python warnings come back too and are issued here, under this process's filters and display: a spawned
process starts with Python's own display, so ``redsim bench scaling`` printed each size's warnings with their file,
line and source line instead of the command line's one ``redsim: warning: ...`` line, and again for every size.
"""

from __future__ import annotations

import multiprocessing
import traceback
import warnings
from collections.abc import Callable
from typing import Any

Said = tuple[str, type[Warning], str, int]
"""A warning the spawned process issued: its message, category, file and line."""

_REGISTRY: dict[object, object] = {}
"""The once-per-location memory of the warnings issued here on a process's behalf (Python's ``default`` action)."""


def _send(function: Callable[[Any], Any], argument: Any, pipe: Any) -> None:
    """``function(argument)`` sent through ``pipe`` as ((True, value), warnings), or ((False, the exception, its
    traceback), warnings); the warnings are those it issued (:data:`Said`), each once."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")  # all of them go back: the parent's filters choose what is shown
        try:
            outcome: tuple[Any, ...] = (True, function(argument))
        except BaseException as err:  # the parent raises it (KeyboardInterrupt too: the parent ends the run)
            outcome = (False, err, traceback.format_exc())
    said = list(dict.fromkeys((str(w.message), w.category, w.filename, w.lineno) for w in caught))
    pipe.send((outcome, said))


def _issue(said: list[Said]) -> None:
    """Issue a process's warnings in this process, where they were issued there."""
    for text, category, filename, lineno in said:
        warnings.warn_explicit(text, category, filename, lineno, registry=_REGISTRY)


def alone(function: Callable[[Any], Any], argument: Any) -> Any:
    """``function(argument)`` in a fresh spawned process (its peak memory is its own), its exception raised here and its
    warnings issued here.

    A ``multiprocessing.Pool`` waits forever for a worker the kernel killed; this returns on any end of the process
    and stops it when the caller is interrupted.

    Raises:
        ChildProcessError: the process ended without a result; the message has its exit code (-9: SIGKILL).
    """
    context = multiprocessing.get_context("spawn")
    receive, send = context.Pipe(duplex=False)
    process = context.Process(target=_send, args=(function, argument, send))
    process.start()
    send.close()
    try:
        message = receive.recv()
    except EOFError:
        process.join()
        raise ChildProcessError(f"its process ended without a result (exit code {process.exitcode})") from None
    except BaseException:
        process.kill()  # the caller was interrupted (Ctrl-C, SIGTERM): the child does not outlive it
        raise
    finally:
        receive.close()
        process.join()
    outcome, said = message
    _issue(said)
    if not outcome[0]:
        outcome[1].add_note(f"in the spawned process:\n{outcome[2]}")
        raise outcome[1]
    return outcome[1]


__all__ = ["alone"]
