"""Progress bars that stay readable in a log file.

tqdm redraws its bar at most every 0.1 s; on a terminal a redraw overwrites the line, but written to a file or
a pipe (a batch job's log, CI) every redraw stays: a 10^4-step fit wrote ~1.2 MB of bars. :func:`progress_bar`
redraws at most every :data:`LOG_INTERVAL` seconds there, unless the user set ``TQDM_MININTERVAL``. Its callers
set a postfix with ``refresh=False`` and let ``update`` draw it (a refreshing ``set_postfix`` ignores the interval).
"""

from __future__ import annotations

import os
import sys
from typing import Any

LOG_INTERVAL = 30.0  # [s] between redraws of a bar written to a file or pipe


def progress_bar(**options: Any) -> Any:
    """A ``tqdm.auto`` bar (a widget in notebooks) with ``options``; redrawn every :data:`LOG_INTERVAL` s at most
    when its stream (``file``, default stderr) is not a terminal."""
    from tqdm.auto import tqdm

    stream = options.get("file") or sys.stderr
    is_terminal = getattr(stream, "isatty", lambda: False)()
    in_notebook = any(kind.__module__ == "tqdm.notebook" for kind in tqdm.__mro__)
    if not (is_terminal or in_notebook) and "TQDM_MININTERVAL" not in os.environ:
        options.setdefault("mininterval", LOG_INTERVAL)
        options.setdefault("maxinterval", LOG_INTERVAL)  # tqdm's monitor thread redraws a bar idle this long
    return tqdm(**options)
