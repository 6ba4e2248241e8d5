"""Who may talk to the server, and what they may see (docs/guides/security.md).

Two independent guards:
- CURVE (ZeroMQ's authenticated encryption, RFC 26/CurveZMQ) on the socket: with
  `ServerOptions.keys_dir`, the ROUTER is a CURVE server with the secret key of
  `keys_dir/server.key_secret`, and a ZAP handler (pyzmq's ThreadAuthenticator) admits only
  clients whose public key is a certificate in `keys_dir/authorized/`. It protects the
  traffic (frames, Results) from eavesdroppers and keeps unknown peers off the socket: their
  handshake fails before any message reaches the server.
- Session tokens (SPEC.md section 4, "session tokens"): a display sees a session's Results
  only with that session's token or the server's admin token, and a capture Hello resumes or
  replaces an existing session only with them. They protect sessions from each other, also
  among clients that CURVE admits (or on a loopback server without keys).

Exposure: a server bound to anything but loopback without keys is refused
(`InsecureBindError`) unless `insecure` is set, which logs a warning on every start.
"""

from __future__ import annotations

import hmac
import ipaddress
import logging
import os
import shutil
from pathlib import Path

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

from arlight.protocols import TOKEN_RE, Error
from arlight.protocols.curve import KeyFileError, load_secret_key

log = logging.getLogger(__name__)

SERVER_KEY = "server"  # DIR/server.key (public), DIR/server.key_secret
CLIENT_KEY = "client"
AUTHORIZED = "authorized"  # DIR/authorized/*.key: the client public keys the server admits


class SecurityError(ValueError):
    """A key, token or exposure problem; the message names the flag and how to fix it."""


class InsecureBindError(SecurityError):
    """A non-loopback bind without CURVE keys (and without `insecure`)."""


def tokens_equal(given: str | None, expected: str | None) -> bool:
    """Constant-time comparison; False when either is None."""
    if given is None or expected is None:
        return False
    return hmac.compare_digest(given.encode(), expected.encode())


def unauthorized_error(session: str, role: str) -> Error:
    """The Error refusing a Hello whose token does not admit it to `session` (a "display"
    watching it, or a "capture" client resuming or replacing it)."""
    if role == "display":
        what = (
            f"watching session {session!r} needs its token: give the one its capture "
            "client printed (`arlight display --token T`) or the server's admin token"
        )
    else:
        what = (
            f"session {session!r} exists and belongs to another capture client: resuming "
            "or replacing it needs its token (`arlight stream --token T`) or the "
            "admin token; or choose another --session"
        )
    return Error(code="unauthorized", field="hello.config.token", message=what)


def read_token_file(path: str, flag: str) -> str:
    """The token in a file (surrounding whitespace ignored); SecurityError naming `flag`."""
    try:
        text = Path(path).read_text(encoding="utf-8").strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise SecurityError(f"{flag}: cannot read {path!r}: {exc}") from None
    if not TOKEN_RE.fullmatch(text):
        raise SecurityError(
            f"{flag}: {path!r} must hold one token of 16..128 characters "
            'from A-Z a-z 0-9 _ - (make one with: python -c "import secrets; '
            'print(secrets.token_urlsafe(24))")'
        )
    return text


def is_loopback(address: str) -> bool:
    """True for an address only this machine can reach: tcp://127.x.x.x, tcp://[::1],
    tcp://localhost, ipc:// and inproc://. tcp://* and tcp://0.0.0.0 (every interface), other
    addresses and interface names are not."""
    if address.startswith(("ipc://", "inproc://")):
        return True
    if not address.startswith("tcp://"):
        return False
    host = address[len("tcp://") :].rsplit(":", 1)[0]
    if ";" in host:  # tcp://SOURCE;HOST:PORT (connect syntax): judge the host
        host = host.rsplit(";", 1)[1]
    host = host.strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # "*", an interface name, a host name


def check_exposure(bind: str, keys_dir: str | None, insecure: bool) -> None:
    """Refuse (InsecureBindError) a bind other hosts can reach without CURVE keys, unless
    `insecure`; then warn (every start)."""
    if keys_dir is not None or is_loopback(bind):
        return
    if not insecure:
        raise InsecureBindError(
            f"--bind {bind} is reachable from other machines, but the server has no keys: "
            "anyone could stream into it and, with a session's token, watch it, all in the "
            "clear. Make keys with `arlight keys generate DIR` and run `arlight serve --bind "
            f"{bind} --keys DIR` (clients: --server-key DIR/server.key --client-key "
            "DIR/client.key_secret), bind tcp://127.0.0.1:PORT, or accept the risk with "
            "--insecure"
        )
    log.warning(
        "--insecure: %s is reachable from other machines without encryption or "
        "client authentication (camera frames and Results travel in the clear); use "
        "`arlight keys generate DIR` and --keys DIR instead",
        bind,
    )


class _ZapLog(logging.LoggerAdapter):
    """pyzmq's ZAP handler logs every decision at DEBUG; a refused client is worth a WARNING
    for the operator (which public key knocked; add it with `arlight keys add` if wanted)."""

    def debug(self, msg, *args, **kwargs):
        try:
            text = str(msg) % args if args else str(msg)
        except (TypeError, ValueError):
            text = str(msg)
        if text.startswith("DENIED"):
            self.warning("refused a client: %s", text)
        else:
            super().debug(msg, *args, **kwargs)


class CurveServer:
    """The server side of CURVE: the server's keys and the ZAP handler that admits the public
    keys in `keys_dir/authorized/` (read at start; restart the server after adding keys)."""

    def __init__(self, keys_dir: str):
        folder = Path(keys_dir)
        try:
            self.public, self.secret = load_secret_key(
                str(folder / f"{SERVER_KEY}.key_secret"), "--keys"
            )
        except KeyFileError as exc:
            raise SecurityError(f"{exc}; make keys with `arlight keys generate DIR`") from None
        self.authorized = folder / AUTHORIZED
        if not self.authorized.is_dir() or not any(self.authorized.glob("*.key")):
            raise SecurityError(
                f"--keys: {str(self.authorized)!r} holds no client key "
                f"(*.key): add one with `arlight keys add {keys_dir} NAME`"
            )
        self._auth: ThreadAuthenticator | None = None

    def start(self, context: zmq.Context) -> None:
        self._auth = ThreadAuthenticator(
            context, log=_ZapLog(logging.getLogger(__name__ + ".zap"), {})
        )
        self._auth.start()
        self._auth.configure_curve(domain="*", location=str(self.authorized))

    def apply(self, sock: zmq.Socket) -> None:
        """Make `sock` a CURVE server (before bind)."""
        sock.curve_secretkey = self.secret
        sock.curve_publickey = self.public
        sock.curve_server = True

    def stop(self) -> None:
        if self._auth is not None:
            self._auth.stop()
            self._auth = None


# --------------------------------------------------------------------------- key files


def _private(path: str) -> None:
    os.chmod(path, 0o600)  # a secret key: readable by its owner only


def generate_keys(folder: str) -> list[Path]:
    """`arlight keys generate DIR`: server and client certificates (zmq.auth format) and
    DIR/authorized/client.key. Refuses (SecurityError) to overwrite existing keys."""
    out = Path(folder)
    existing = [
        out / f"{n}.key{s}"
        for n in (SERVER_KEY, CLIENT_KEY)
        for s in ("", "_secret")
        if (out / f"{n}.key{s}").exists()
    ]
    if existing:
        raise SecurityError(
            f"{str(existing[0])!r} exists: `arlight keys generate` never "
            "overwrites keys; choose another DIR, or add clients with "
            f"`arlight keys add {folder} NAME`"
        )
    out.mkdir(parents=True, exist_ok=True)
    (out / AUTHORIZED).mkdir(exist_ok=True)
    written = []
    for name in (SERVER_KEY, CLIENT_KEY):
        public, secret = zmq.auth.create_certificates(str(out), name)
        _private(secret)
        written += [Path(public), Path(secret)]
    written.append(Path(shutil.copy(out / f"{CLIENT_KEY}.key", out / AUTHORIZED)))
    return written


def add_client_key(folder: str, name: str) -> list[Path]:
    """`arlight keys add DIR NAME`: DIR/NAME.key, DIR/NAME.key_secret and
    DIR/authorized/NAME.key (a running server reads authorized/ at start)."""
    out = Path(folder)
    if not (out / f"{SERVER_KEY}.key").exists():
        raise SecurityError(
            f"{folder!r} has no server.key: make the keys first with "
            f"`arlight keys generate {folder}`"
        )
    if not name or name == SERVER_KEY or not all(c.isalnum() or c in "_.-" for c in name):
        raise SecurityError(
            f"NAME must be letters, digits, _ . - and not {SERVER_KEY!r}, got {name!r}"
        )
    if (out / f"{name}.key").exists() or (out / AUTHORIZED / f"{name}.key").exists():
        raise SecurityError(f"a key named {name!r} exists in {folder!r}; choose another NAME")
    (out / AUTHORIZED).mkdir(exist_ok=True)
    public, secret = zmq.auth.create_certificates(str(out), name)
    _private(secret)
    return [Path(public), Path(secret), Path(shutil.copy(public, out / AUTHORIZED))]
