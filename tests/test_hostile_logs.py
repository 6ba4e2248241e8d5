"""Peer-supplied text cannot forge or flood the server's log (issue 39, item 6): a Bye's
reason and a client Error's code, field and message are escaped onto one line, and client
Errors share the rate limit of the Errors the server sends (20 lines a second, then one line
counting the rest). Real server, real sockets on loopback, a legitimate session beside."""

from __future__ import annotations

import logging
import time

from hostile_support import LegitStream
from streaming_support import RawPeer, identity_step, wait_for

from arlight.protocols import Bye, Error

FORGED = "arlight serve: admin token FORGEDFORGEDFORGED"


def test_a_bye_reason_cannot_forge_a_log_line(make_server, caplog):
    server = make_server(identity_step())
    peer = RawPeer(server.connect_address)
    peer.hello("forger")
    with caplog.at_level(logging.INFO, logger="arlight.server"):
        peer.send_message(Bye(f"done\n{FORGED}\r\x1b[2K\u2028x"))
        wait_for(lambda: "said Bye" in caplog.text, 10, "the Bye's log line")
        peer.send_message(Error("internal", f"oops\n{FORGED}", field="a\nb"))
        wait_for(lambda: "reported an error" in caplog.text, 10, "the Error's log line")
    peer.close()
    for record in caplog.records:
        text = record.getMessage()
        assert "\n" not in text and "\r" not in text and "\x1b" not in text, text
    lines = caplog.text.splitlines()
    assert not [line for line in lines if line.startswith(FORGED)]
    assert any("done\\n" + FORGED in line for line in lines)


def test_client_errors_are_rate_limited(make_server, caplog):
    server = make_server(identity_step())
    flood = RawPeer(server.connect_address)
    with caplog.at_level(logging.INFO, logger="arlight.server"):
        with LegitStream(server.connect_address) as legit:
            start = time.monotonic()
            for i in range(5000):
                flood.send_message(Error("internal", f"{i} " + "x" * 4000))
            wait_for(lambda: server.stats.messages >= 5000, 30, "the flood to be read")
            time.sleep(1.2)  # the last second's count is logged when the next one begins
            elapsed = time.monotonic() - start
        legit.assert_served()
    flood.close()
    reported = [r for r in caplog.records if "reported an error" in r.getMessage()]
    assert 1 <= len(reported) <= 20 * (elapsed + 1)
    assert "not logged" in caplog.text
    assert len(caplog.text) < 2_000_000  # 5000 x 4 KB logged raw was 21 MB
