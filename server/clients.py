"""Per-client limits (issue 39, item 3): a client is the key that CURVE authenticated it with
(ZAP's User-Id), or without keys its network address; every connection it opens counts as
the same client. Before, one connection filled `--max-sessions` with 32 capture Hellos of
distinct names in 0.5 s and held them by saying Hello again every minute.

- a client holds at most `max_sessions_per_client` sessions (the ones its Hellos created,
  until they close or expire);
- a client's Hellos are rate-limited: a bucket of `HELLO_BURST` refilled at
  `hellos_per_client_s` a second; a Hello takes one token, and one more per
  HELLO_TRIANGLES_PER_TOKEN triangles of its virtual scene, up front; once handled, the time it
  held the I/O thread is charged beyond that (`HelloLimiter.settle`), so a client's Hellos hold
  the I/O thread at most HELLO_IO_SHARE of the time on a machine of any speed.

Local peers (loopback, ipc) without keys share one address, so each of their connections is a
client of its own: a local program that opens many connections is held only by
`--max-sessions`; give local clients keys (`arlight keys`) to count them by key. Times:
time.monotonic().
"""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass

import zmq

HELLO_BURST = 20  # Hellos a client may send at once before the rate applies
FORGET_AFTER_S = 300.0  # a client's bucket is dropped once full and this old


def client_of(frame: zmq.Frame, identity: bytes) -> str:
    """The client a received message came from: "key:Z85" under CURVE, else "addr:IP" for a
    remote address, else (loopback, ipc, inproc: every local program shares the address)
    "conn:HEX", the connection itself."""
    for prop, prefix in (("User-Id", "key:"), ("Peer-Address", "addr:")):
        try:
            value = frame.get(prop)
        except (zmq.ZMQError, AttributeError, TypeError):
            continue
        if value and not (prefix == "addr:" and _local(str(value))):
            return prefix + str(value)
    return "conn:" + identity.hex()


def _local(address: str) -> bool:
    try:
        ip = ipaddress.ip_address(address.strip("[]"))
    except ValueError:
        return True  # not an IP address: not a remote peer's
    mapped = getattr(ip, "ipv4_mapped", None)
    return (mapped or ip).is_loopback


# A Hello with a virtual scene costs the I/O thread time with its triangles (checks, the cost
# model's crowding count: 2 M triangles, 0.9 s on the development machine, docs/reliability.md);
# it takes one token more per HELLO_TRIANGLES_PER_TOKEN triangles up front, about what
# HELLO_IO_SHARE allows there.
HELLO_TRIANGLES_PER_TOKEN = 200_000
# The most of the I/O thread's time a client's Hellos may take: a token stands for
# HELLO_IO_SHARE / rate seconds of it. The triangle count above is only the up-front estimate:
# CI's two busy cores took about twice the development machine's 0.9 s (docs/reliability.md).
HELLO_IO_SHARE = 0.4


def hello_cost(triangles: int) -> float:
    """The tokens a Hello whose scene holds `triangles` triangles takes."""
    return 1.0 + triangles / HELLO_TRIANGLES_PER_TOKEN


@dataclass
class Bucket:
    tokens: float
    stamp: float


class HelloLimiter:
    """Token buckets of Hellos per client."""

    def __init__(self, rate_per_s: float, burst: int = HELLO_BURST):
        self.rate_per_s = rate_per_s
        self.burst = burst
        self._buckets: dict[str, Bucket] = {}

    def allow(self, client: str, now: float, cost: float = 1.0) -> bool:
        """A Hello from `client` now, costing `cost` tokens (`hello_cost`): False when its
        bucket holds fewer (refused)."""
        bucket = self._buckets.get(client)
        if bucket is None:
            bucket = self._buckets[client] = Bucket(float(self.burst), now)
        self._refill(bucket, now)
        if bucket.tokens < cost:
            return False
        bucket.tokens -= cost
        return True

    def settle(self, client: str, now: float, cost: float, busy_s: float) -> None:
        """Charge a Hello that `allow` let in for `cost` tokens with the `busy_s` seconds it then
        held the I/O thread, beyond that cost: the bucket may fall below zero (down to -burst),
        and the client's next Hellos are refused until it has refilled."""
        bucket = self._buckets.get(client)
        if bucket is None:
            return
        self._refill(bucket, now)
        owed = busy_s * self.rate_per_s / HELLO_IO_SHARE - cost
        if owed > 0:
            bucket.tokens = max(-float(self.burst), bucket.tokens - owed)

    def _refill(self, bucket: Bucket, now: float) -> None:
        elapsed = max(0.0, now - bucket.stamp)
        bucket.tokens = min(self.burst, bucket.tokens + elapsed * self.rate_per_s)
        bucket.stamp = max(bucket.stamp, now)

    def forget_idle(self, now: float) -> None:
        """Drop the buckets of clients silent long enough to be full again (housekeeping)."""
        for client, bucket in list(self._buckets.items()):
            if now - bucket.stamp > FORGET_AFTER_S:
                del self._buckets[client]
