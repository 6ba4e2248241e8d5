"""A loopback test server in a process of its own (issue 39): an attack that aborts a process
must not take pytest with it. Run as `python tests/hostile_server.py '{"option": value}'`:
it prints the port, serves with the identity step (tests/streaming_support.py) until its
standard input closes, then stops and exits 0."""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from streaming_support import identity_step, server_options  # noqa: E402

from arlight.server.server import Server  # noqa: E402


def main() -> int:
    options = json.loads(sys.argv[1]) if len(sys.argv) > 1 else {}
    delay_s = options.pop("delay_s", 0.0)
    server = Server(server_options(**options), process=identity_step(delay_s)).start()
    print(server.port, flush=True)
    sys.stdin.read()
    server.stop(timeout=15)
    return 0


if __name__ == "__main__":
    sys.exit(main())
