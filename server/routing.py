"""Routing ids a peer cannot guess (issue 39, item 1).

libzmq's ROUTER names each peer that does not choose an id with 5 bytes: a zero, then a
32-bit counter that starts at a value from the C library's `rand()` when the socket is made
and goes up by one per connection. Unseeded, `rand()` gives the same start in every process
(glibc: 00 6b8b4567, 00 6b8b4568, ...), and a client may choose its own id, any bytes: a peer
that took the next ids made the next ordinary connection fail libzmq's assertion
(`socket_base.cpp:2113`) and abort the whole server. `seed_routing_ids()` seeds `rand()` from
the operating system's random source just before the ROUTER is made, so its counter starts
at one of 2^32 values no peer can predict (occupying the next id by chance: 1 in 2^32 per
connection; finding one in use by probing: about 2^31 connections).
"""

from __future__ import annotations

import ctypes
import logging
import secrets

log = logging.getLogger(__name__)


def seed_routing_ids() -> bool:
    """Seed the C library's `rand()` (which libzmq's ROUTER draws its first automatic routing
    id from) with 32 bits from `secrets`; call just before making the ROUTER. False (logged)
    where the C library cannot be reached, e.g. on Windows."""
    try:
        libc = ctypes.CDLL(None)  # the process's own symbols: the C library libzmq uses
        srand = libc.srand
    except (OSError, AttributeError, TypeError):
        log.warning(
            "could not seed the C library's rand(): libzmq's routing ids stay predictable, "
            "and a peer that occupies them can abort the server; bind loopback or use --keys"
        )
        return False
    srand.argtypes = [ctypes.c_uint]
    srand.restype = None
    srand(secrets.randbits(32))
    return True
