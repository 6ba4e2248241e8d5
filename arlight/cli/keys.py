"""`arlight keys`: CURVE keys for `arlight serve --keys` and its clients."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from arlight.server.security import add_client_key, generate_keys


def add_parser(sub) -> None:
    keys = sub.add_parser(
        "keys",
        help="make CURVE keys for `arlight serve --keys` and its clients",
        description="Make ZeroMQ CURVE certificates (zmq.auth format). `generate DIR` writes "
        "DIR/server.key (public: give it to clients), DIR/server.key_secret "
        "(the server's only), DIR/client.key and DIR/client.key_secret (a "
        "client's pair) and DIR/authorized/client.key (the keys the server "
        "admits). `add DIR NAME` makes another client's pair and authorises it.",
    )
    verbs = keys.add_subparsers(dest="keys_command", required=True, metavar="ACTION")
    gen = verbs.add_parser("generate", help="server and first client keys in DIR")
    gen.add_argument("dir", metavar="DIR")
    add = verbs.add_parser("add", help="another client's keys, authorised in DIR/authorized/")
    add.add_argument("dir", metavar="DIR")
    add.add_argument("name", metavar="NAME", help="the client's name (letters, digits, _ . -)")
    keys.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.keys_command == "generate":
        written = generate_keys(args.dir)
        d = Path(args.dir)
        print(
            f"arlight keys: wrote {', '.join(str(p) for p in written)}\n"
            f"  server:  arlight serve --bind tcp://*:5555 --keys {d}\n"
            f"  clients: --server-key {d / 'server.key'} --client-key "
            f"{d / 'client.key_secret'} (copy both files to the client; *.key_secret files "
            "are secrets)",
            file=sys.stderr,
        )
    else:
        written = add_client_key(args.dir, args.name)
        print(
            f"arlight keys: wrote {', '.join(str(p) for p in written)}; restart the "
            f"server to admit it (client: --client-key {written[1]})",
            file=sys.stderr,
        )
    return 0
