"""`rvs-server` and `python -m rvs_server`: the server's entry point.

SIGINT and SIGTERM are blocked here, before the seconds of imports (NumPy, Open3D, ZeroMQ,
pycolmap) the server needs, and unblocked once the event loop handles them: a signal at any moment
of start-up waits, pending, and then ends the server cleanly with exit status 0. Blocking rather
than catching matters because pycolmap's logging library installs its own SIGTERM handler when
imported (it prints a C stack and kills the process); the loop's handler replaces it. Only the
interpreter's own first few tens of milliseconds remain uncovered.
"""
from __future__ import annotations

import logging
import os
import signal
import sys


def main(argv: list[str] | None = None) -> int:
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    from .app import main as run_server
    code = run_server(argv)
    # The exit status is the server's own. The interpreter's finalisation runs C++ static destructors
    # (Open3D reports a tensor an interrupted ray cast left behind) that turned a clean quit after a
    # break into exit status 1; everything is written and closed by now, so skip them.
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    sys.exit(main())
