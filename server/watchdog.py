"""An exit deadline that a stage holding the interpreter cannot delay (issue 39, item 2).

`arlight serve` stops on SIGTERM or SIGINT within `--shutdown-grace` + WORKER_EXIT_WAIT_S
(arlight/cli/serve.py), but Python runs a signal handler only when the main thread gets the
interpreter lock: a worker inside a C call that keeps it (Open3D's ray casting over a
crowded scene) held the process 38 s after SIGTERM. The C-level handler still writes the
signal's number to the wakeup fd (`signal.set_wakeup_fd`), without the lock; a small
watchdog process reads it and, if the server has not exited `limit_s` seconds later, kills
it (SIGKILL) and says why on stderr. It ends by itself when the server exits (the pipe
closes).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys

_WATCHDOG = r"""
import os, select, signal, sys, time
fd, pid, limit = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3])
signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole process group
if not os.read(fd, 64):
    sys.exit(0)  # the server exited without a signal
deadline = time.monotonic() + limit
while (left := deadline - time.monotonic()) > 0:
    if select.select([fd], [], [], left)[0] and not os.read(fd, 64):
        sys.exit(0)  # the server exited in time
try:
    os.kill(pid, signal.SIGKILL)
except ProcessLookupError:
    sys.exit(0)
sys.stderr.write(
    f"arlight serve: still running {limit:g} s after the stop signal (a worker inside a "
    "stage that holds the interpreter); killed\n"
)
"""


def start_exit_watchdog(limit_s: float) -> subprocess.Popen:
    """From the main thread, after the signal handlers are installed: a watchdog process
    that kills this one `limit_s` seconds after the first signal Python handles, unless it
    has exited by then. Returns the watchdog (it exits with this process)."""
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
    watchdog = subprocess.Popen(
        [sys.executable, "-c", _WATCHDOG, str(read_fd), str(os.getpid()), str(limit_s)],
        pass_fds=(read_fd,),
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
    )
    os.close(read_fd)
    return watchdog
