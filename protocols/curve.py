"""CURVE key files for the transport (SPEC.md section 1, "Security"): zmq.auth certificates.

`arlight keys generate DIR` writes them (server/security.py): NAME.key holds a public key,
NAME.key_secret the public and the secret key. A client needs the server's public key (it
authenticates the server: no one else can answer) and its own secret certificate (the server
admits only the public keys in its authorized/ folder). Errors name the command-line flag.
"""

from __future__ import annotations

from dataclasses import dataclass

import zmq
import zmq.auth


class KeyFileError(ValueError):
    """A key file that cannot be used; the message names the flag and the file."""


def load_public_key(path: str, flag: str) -> bytes:
    """The public key (Z85, 40 bytes) of a certificate, NAME.key or NAME.key_secret."""
    try:
        public, _ = zmq.auth.load_certificate(path)
    except (OSError, ValueError) as exc:
        raise KeyFileError(f"{flag}: cannot read the key file {path!r}: {exc}") from None
    return public


def load_secret_key(path: str, flag: str) -> tuple[bytes, bytes]:
    """(public, secret) of a secret certificate, NAME.key_secret."""
    try:
        public, secret = zmq.auth.load_certificate(path)
    except (OSError, ValueError) as exc:
        raise KeyFileError(f"{flag}: cannot read the key file {path!r}: {exc}") from None
    if not secret:
        raise KeyFileError(
            f"{flag}: {path!r} holds no secret key: give the NAME.key_secret "
            "file (NAME.key is the public half)"
        )
    return public, secret


@dataclass(frozen=True)
class ClientKeys:
    """A client's CURVE keys: the server's public key and the client's own pair (Z85)."""

    server_public: bytes
    public: bytes
    secret: bytes

    @classmethod
    def load(cls, server_key: str, client_key: str) -> ClientKeys:
        """From --server-key DIR/server.key and --client-key DIR/client.key_secret."""
        public, secret = load_secret_key(client_key, "--client-key")
        return cls(load_public_key(server_key, "--server-key"), public, secret)

    def apply(self, sock: zmq.Socket) -> None:
        """Make `sock` a CURVE client of the server (before connect)."""
        sock.curve_serverkey = self.server_public
        sock.curve_publickey = self.public
        sock.curve_secretkey = self.secret
