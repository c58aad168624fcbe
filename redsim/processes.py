"""Run a function in a fresh spawned process and get its result or its exception back: where a benchmark's step needs
its own process (its peak memory its own) and must not wait forever for one the kernel killed, as a
``multiprocessing.Pool`` does. Importing it does not import torch.
"""

from __future__ import annotations

import multiprocessing
import traceback
from collections.abc import Callable
from typing import Any


def _send(function: Callable[[Any], Any], argument: Any, pipe: Any) -> None:
    """``function(argument)`` sent through ``pipe`` as (True, value), or (False, the exception, its traceback)."""
    try:
        pipe.send((True, function(argument)))
    except BaseException as err:  # the parent raises it (KeyboardInterrupt too: the parent ends the run)
        pipe.send((False, err, traceback.format_exc()))


def alone(function: Callable[[Any], Any], argument: Any) -> Any:
    """``function(argument)`` in a fresh spawned process (its peak memory is its own), its exception raised here.

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
    if not message[0]:
        message[1].add_note(f"in the spawned process:\n{message[2]}")
        raise message[1]
    return message[1]


__all__ = ["alone"]
