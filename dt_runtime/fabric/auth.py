"""Signed maintenance messages: only a holder of the service's key can ack, clear or raise a request.

The MAC is HMAC-SHA256 with the key of `bus.auth.key_file` over the message's key expression, a
newline and the canonical JSON of the payload without `sig` (`canonical`), carried in the payload
as `"sig": "hmac-sha256:<hex>"`. Acks and dones are refused when their `t` is further than
`bus.auth.max_age_s` from the receiver's clock; requests are not time-checked. What is signed,
why signatures rather than Zenoh's authentication, where the key lives and who holds it:
docs/bus.md ("Who can do what").
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
    """`bus.auth`: where the service's key is, and how old a signed ack or 'done' may be.

    `key_file`: the key's path (None: `default_key_file()`; `~` is expanded, a relative path is
    taken from the working directory). `max_age_s`: s, how far an ack's or a done's `t` may lie from
    the receiver's clock, in (0, 86400].
    """

    key_file: str | None = None  # None: default_key_file(); `~` is expanded, relative to the working directory
    max_age_s: float = Field(300.0, gt=0, le=86_400)


def default_key_file() -> Path:
    """$XDG_CONFIG_HOME/cobot-dt/bus.key, else ~/.config/cobot-dt/bus.key: the user's own."""
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "cobot-dt" / "bus.key"


def key_path(cfg: AuthConfig) -> Path:
    """The key file `cfg` names: `key_file` with `~` expanded, else `default_key_file()`.

    Parameters
    ----------
    cfg : AuthConfig
        The `bus.auth` section.

    Returns
    -------
    Path
        The path (relative ones stay relative to the working directory); not checked to exist.
    """
    return Path(os.path.expanduser(cfg.key_file)) if cfg.key_file else default_key_file()


def canonical(payload: Mapping[str, Any]) -> bytes:
    """The bytes a signature covers: sorted keys, no spaces, the payload without `sig`.

    Parameters
    ----------
    payload : mapping of str to JSON values
        A message as decoded from the bus; its `sig`, if any, is left out.

    Returns
    -------
    bytes
        ASCII JSON (non-ASCII characters escaped).
    """
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

    The key is read once, in the constructor; `path` is the file it came from.

    Parameters
    ----------
    cfg : AuthConfig
        The `bus.auth` section: the key file and the largest age of an ack or done.
    create : bool
        Write a new key (64 random hex digits, 0600, its directory made 0700 if missing) when there
        is none: the daemon and the consumer do; `dt ack` does not (a new key could not be the
        service's).

    Raises
    ------
    ConfigError
        Naming the file, when the key is missing (and not created), cannot be created or read,
        gives the group or others any access, or is shorter than 16 bytes.
    """

    def __init__(self, cfg: AuthConfig, *, create: bool = True):
        self.cfg = cfg
        self.path = key_path(cfg)
        self._key = _load_key(self.path, create)

    def mac(self, key_expr: str, payload: Mapping[str, Any]) -> str:
        """The signature of `payload` on `key_expr`, as carried in `sig`.

        Parameters
        ----------
        key_expr : str
            The key the message is put on (`dt/<cell>/<robot>/...`): it is signed too.
        payload : mapping of str to JSON values
            The message; its `sig`, if any, is not covered.

        Returns
        -------
        str
            `hmac-sha256:` followed by 64 hex digits.
        """
        digest = hmac.new(self._key, key_expr.encode() + b"\n" + canonical(payload), hashlib.sha256)
        return _SCHEME + digest.hexdigest()

    def sign(self, key_expr: str, payload: Mapping[str, Any]) -> bytes:
        """The encoded message with its signature: signed as the receiver will decode it (the
        JSON round trip turns numpy values, tuples and NaN into what the receiver sees).

        Parameters
        ----------
        key_expr : str
            The key the message will be put on.
        payload : mapping of str to any
            The message; a `sig` it carries is replaced.

        Returns
        -------
        bytes
            Compact UTF-8 JSON (`session.encode`) with `sig` added.
        """
        body = json.loads(encode(payload))
        body.pop(SIG, None)
        body[SIG] = self.mac(key_expr, body)
        return encode(body)

    def check(self, key_expr: str, msg: Mapping[str, Any], *, fresh: bool) -> str | None:
        """None if `msg` (received on `key_expr`) is signed with this key (and, when `fresh`,
        its `t` is within max_age_s of now); else why not, in words.

        Parameters
        ----------
        key_expr : str
            The key the message arrived on.
        msg : mapping of str to JSON values
            The decoded message, with its `sig`.
        fresh : bool
            Also require a finite `t` (epoch s) within `cfg.max_age_s` of this host's clock (acks
            and dones; not requests, which are republished for hours).

        Returns
        -------
        str or None
            None when the message is accepted; else the reason (not signed, signature does not
            match, no time, too old or in the future), for the log.
        """
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
