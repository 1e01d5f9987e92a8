"""Signed maintenance messages: only a holder of the service's key can ack, clear or raise a request.

Why signatures and not Zenoh's own authentication. On the default bus (a peer on loopback) any
local process can connect, read a request's `uid` and publish `.../maintenance/done/<id>`: the
black-box probe cleared a request "by mallory" that way. Zenoh's user/password authentication
works per link: every reader (a dashboard, `dt status` over the bus) would need a password,
anyone holding one could still publish anything unless access-control rules by user name were
added, and behind a router the daemon sees the router, not who wrote the message. A signature
travels with the message, end to end, through any router, and is checked where the action is
applied; readers need nothing; and it adds to, never replaces, the TLS and access control of a
plant network (configs/bus_tls_acl_example.yaml).

What is signed: every maintenance message that changes something, i.e. the daemon's requests,
and the consumers' acknowledgements (`.../maintenance/ack/<id>`) and confirmations
(`.../maintenance/done/<id>`); the daemon's reliable messages (state, health, correction) too,
so `dt ack` can trust the state it waits for. The MAC is HMAC-SHA256 (RFC 2104) with the key of
`auth.key_file` over the message's key expression, a newline and the canonical JSON of the
payload without `sig` (keys sorted, no spaces: `canonical`), written as `"sig": "hmac-sha256:<hex>"`.
The key expression binds the message to its robot, kind and request id: a signed ack is not a
signed 'done', and a 'done' for robot r1 does not clear robot r2. Acks and dones carry `t`
(epoch s) and are refused when more than `auth.max_age_s` (300 s) away from the receiver's clock:
a recorded message cannot be replayed later. A request is not time-checked (it is republished
until acknowledged, for hours if a consumer is away); consumers de-duplicate it on its uid.

The key: `auth.key_file`, default `$XDG_CONFIG_HOME/cobot-dt/bus.key` (`~/.config/cobot-dt/bus.key`)
of the user the service runs as, 64 random hex digits. The daemon (`Bus`) and the consumer
create it 0600 (in a 0700 directory) when it does not exist; `dt ack --bus` needs it to exist. A
key file that the group or others may read is refused (common.private_files): it may have been
copied. Who can do what: docs/bus.md.
"""
from __future__ import annotations

import hashlib
import hmac
import json
import math
import os
import secrets
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pydantic import Field

from dt_kernel.config import Frozen
from dt_kernel.errors import ConfigError
from dt_runtime.common import private_files
from dt_runtime.fabric.session import encode

SIG = "sig"  # the payload key that carries the signature
_SCHEME = "hmac-sha256:"
_MIN_KEY_BYTES = 16


class AuthConfig(Frozen):
    """`bus.auth`: where the service's key is, and how old a signed ack or 'done' may be."""

    key_file: str | None = None  # None: default_key_file(); `~` is expanded, relative to the working directory
    max_age_s: float = Field(300.0, gt=0, le=86_400)


def default_key_file() -> Path:
    """$XDG_CONFIG_HOME/cobot-dt/bus.key, else ~/.config/cobot-dt/bus.key: the user's own."""
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "cobot-dt" / "bus.key"


def key_path(cfg: AuthConfig) -> Path:
    return Path(os.path.expanduser(cfg.key_file)) if cfg.key_file else default_key_file()


def canonical(payload: Mapping[str, Any]) -> bytes:
    """The bytes a signature covers: sorted keys, no spaces, the payload without `sig`."""
    body = {k: v for k, v in payload.items() if k != SIG}
    return json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True).encode()


def _load_key(path: Path, create: bool) -> bytes:
    where = "bus.auth.key_file"
    allowed = ("a key file only this user can read (mode 0600): run as the service's user, or give "
               "bus.auth.key_file")
    if create and not path.exists():
        try:
            _create_key(path)
        except OSError as exc:
            raise ConfigError(path, where, f"cannot be created ({exc.strerror}: {exc.filename})",
                              "a key file in a directory this user may write (a system user without a home: "
                              "give bus.auth.key_file, e.g. in systemd's StateDirectory)") from exc
    try:
        loose = private_files.looser_than_private(path)
        if loose is not None:
            raise ConfigError(path, where, f"mode {loose:04o}",
                              "0600: other users could read this key, so it may have been copied. Make a new one "
                              f"(rm {path}; the daemon writes a fresh one when it starts; give it to the operators "
                              f"again), or, if nobody else can have read it, chmod 600 {path}")
        key = path.read_bytes().strip()
    except FileNotFoundError as exc:
        raise ConfigError(path, where, "missing", allowed + " (the daemon creates it at its first start)") from exc
    except OSError as exc:
        raise ConfigError(path, where, f"unreadable ({exc.strerror})", allowed) from exc
    if len(key) < _MIN_KEY_BYTES:
        raise ConfigError(path, where, f"{len(key)} bytes", f"a key of at least {_MIN_KEY_BYTES} bytes "
                          "(the daemon writes 64 random hex digits)")
    return key


def _create_key(path: Path) -> None:
    """A new random key at `path`, 0600, whole or not at all: written to a private temporary file
    and linked into place (two processes starting at once agree on the one that was linked)."""
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.unlink(missing_ok=True)  # a crashed start's leftover: the new file must be created 0600
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, private_files.PRIVATE)
    try:
        with os.fdopen(fd, "w", encoding="ascii") as f:
            f.write(secrets.token_hex(32) + "\n")
            f.flush()
            os.fsync(f.fileno())
        try:
            os.link(tmp, path)
        except FileExistsError:
            pass  # another process made it first: its key is the key
    finally:
        tmp.unlink(missing_ok=True)


class Signer:
    """Signs and checks maintenance messages with the key of `cfg` (module docstring).

    `create`: write a new key if there is none (the daemon and the consumer; `dt ack` does not).
    Raises ConfigError naming the file when the key is missing, unreadable or readable by others."""

    def __init__(self, cfg: AuthConfig, *, create: bool = True):
        self.cfg = cfg
        self.path = key_path(cfg)
        self._key = _load_key(self.path, create)

    def mac(self, key_expr: str, payload: Mapping[str, Any]) -> str:
        digest = hmac.new(self._key, key_expr.encode() + b"\n" + canonical(payload), hashlib.sha256)
        return _SCHEME + digest.hexdigest()

    def sign(self, key_expr: str, payload: Mapping[str, Any]) -> bytes:
        """The encoded message with its signature: signed as the receiver will decode it (the
        JSON round trip turns numpy values, tuples and NaN into what the receiver sees)."""
        body = json.loads(encode(payload))
        body.pop(SIG, None)
        body[SIG] = self.mac(key_expr, body)
        return encode(body)

    def check(self, key_expr: str, msg: Mapping[str, Any], *, fresh: bool) -> str | None:
        """None if `msg` (received on `key_expr`) is signed with this key (and, when `fresh`,
        its `t` is within max_age_s of now); else why not, in words."""
        sig = msg.get(SIG)
        if not isinstance(sig, str):
            return "not signed (no 'sig': the sender does not hold the service's key)"
        if not hmac.compare_digest(sig.encode(), self.mac(key_expr, msg).encode()):
            return "signature does not match (signed with another key, or altered on the way)"
        if fresh:
            t = msg.get("t")
            if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t):
                return "signed but carries no time 't'"
            age = time.time() - float(t)
            if abs(age) > self.cfg.max_age_s:
                return (f"signed {age:.0f} s {'ago' if age > 0 else 'in the future'} (bus.auth.max_age_s "
                        f"{self.cfg.max_age_s:g}): a replayed message, or clocks apart")
        return None
