"""A loopback test server in a process of its own (issue 39): an attack that aborts a process
must not take pytest with it. Run as `python tests/hostile_server.py '{"option": value}'`:
it prints the port, serves with the identity step (tests/streaming_support.py) until its
standard input closes, then stops and exits 0. Options beside ServerOptions': delay_s (the
step's), watchdog_s (stop on SIGTERM, killed by server/watchdog.py after that long); sessions
named gil* hold the interpreter lock about a minute a frame."""

from __future__ import annotations

import json
import re
import signal
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from streaming_support import identity_step, server_options  # noqa: E402

from arlight.server.server import Server  # noqa: E402
from arlight.server.watchdog import start_exit_watchdog  # noqa: E402


def gil_step(step):
    """Sessions named gil*: each frame holds the interpreter lock in one C call for about a
    minute (a regular expression backtracking: Python cannot interrupt it), as Open3D's ray
    casting over a crowded scene did."""

    def process(frame, session, render_light, deadline):
        if session.name.startswith("gil"):
            re.match(r"(a|aa)+$", "a" * 42 + "b")
        return step(frame, session, render_light, deadline)

    return process


def main() -> int:
    options = json.loads(sys.argv[1]) if len(sys.argv) > 1 else {}
    delay_s = options.pop("delay_s", 0.0)
    watchdog_s = options.pop("watchdog_s", None)
    process = gil_step(identity_step(delay_s))
    server = Server(server_options(**options), process=process).start()
    if watchdog_s is not None:  # as `arlight serve`: stop on SIGTERM, within the watchdog
        signal.signal(signal.SIGTERM, lambda *_: server.stop(timeout=0))
        start_exit_watchdog(float(watchdog_s))
    print(server.port, flush=True)
    sys.stdin.read()
    server.stop(timeout=15)
    return 0


if __name__ == "__main__":
    sys.exit(main())
