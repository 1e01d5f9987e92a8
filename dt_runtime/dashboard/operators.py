"""Who may acknowledge or close a maintenance request from the dashboard: the operators' token file.

One operator a line, `<name> <token>` (blank lines and `#` comments ignored); the token is at
least 16 characters of letters, digits and `-_.~+/=` (`python -c "import secrets; print(secrets.token_urlsafe())"`),
a name letters, digits and `-_.@`. The page sends the token as `Authorization: Bearer <token>`;
the server finds the operator by it (constant-time comparison, `hmac.compare_digest`) and signs
the ack or 'done' with the bus key under that operator's name, so the daemon records who it was.

The file must be readable by its owner only (0600), as the bus key must: a token others can read
may have been copied, so a looser file is refused (dt_runtime.common.private_files), not
tightened. Errors name the file, the line and what is allowed (ConfigError: `dt dashboard`
exits 2).
"""
from __future__ import annotations

import hmac
import re
from dataclasses import dataclass
from pathlib import Path

from dt_kernel.errors import ConfigError
from dt_runtime.common import private_files

MIN_TOKEN_CHARS = 16
MAX_FILE_BYTES = 64 * 1024
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.@-]{0,63}")
_TOKEN = re.compile(r"[A-Za-z0-9_.~+/=-]{" + str(MIN_TOKEN_CHARS) + ",256}")
_LINE = "one operator a line: '<name> <token>', the name letters, digits and -_.@ (at most 64), the token " \
        f"{MIN_TOKEN_CHARS} to 256 characters of letters, digits and -_.~+/="


@dataclass(frozen=True)
class Operators:
    """The operators of a token file, found by their token."""

    path: Path
    _by_token: tuple[tuple[bytes, str], ...]

    @property
    def names(self) -> list[str]:
        """The operators' names, in file order."""
        return [name for _, name in self._by_token]

    def who(self, token: str | None) -> str | None:
        """The operator whose token this is.

        Every entry is compared (constant time each), so the time taken does not tell which entry came
        close.

        Parameters
        ----------
        token : str or None

        Returns
        -------
        str or None
            The operator's name, or None.
        """
        if not token:
            return None
        given = token.encode("utf-8", "replace")
        found = None
        for tok, name in self._by_token:
            if hmac.compare_digest(tok, given):
                found = name
        return found


def load_operators(path: str | Path) -> Operators:
    """Read the operators' token file.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    Operators

    Raises
    ------
    ConfigError
        Naming the file (and the line) when it is missing, unreadable, readable by others, longer
        than 64 KiB, not UTF-8, malformed, names an operator twice, gives two operators one token, or
        names none.
    """
    p = Path(path)
    where = "--token-file"
    try:
        loose = private_files.looser_than_private(p)
        if loose is not None:
            raise ConfigError(p, where, f"mode {loose:04o}",
                              "0600: other users could read these tokens, so they may have been copied. Make new "
                              f"tokens in a new file (chmod 600 before writing them), or, if nobody else can have "
                              f"read it, chmod 600 {p}")
        raw = p.read_bytes()[: MAX_FILE_BYTES + 1]
    except FileNotFoundError as exc:
        raise ConfigError(p, where, "missing", "a file of operators' tokens, mode 0600 (" + _LINE + ")") from exc
    except OSError as exc:
        raise ConfigError(p, where, f"unreadable ({exc.strerror})", "a file this user can read, mode 0600") from exc
    if len(raw) > MAX_FILE_BYTES:
        raise ConfigError(p, where, f"more than {MAX_FILE_BYTES} bytes", "a short file: " + _LINE)
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(p, where, "not UTF-8 text", _LINE) from exc
    entries: list[tuple[bytes, str]] = []
    for n, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 2 or not _NAME.fullmatch(parts[0]) or not _TOKEN.fullmatch(parts[1]):
            shown = parts[0] if parts else line  # never the token itself in a message
            raise ConfigError(p, f"line {n}", f"an entry for {shown!r}", _LINE)
        name, token = parts
        if any(hmac.compare_digest(token.encode(), t) for t, _ in entries):
            raise ConfigError(p, f"line {n}", f"the token of {name!r}", "a token of its own for every operator "
                              "(two operators share one: the record could not say who it was)")
        if name in (m for _, m in entries):
            raise ConfigError(p, f"line {n}", name, "each operator once")
        entries.append((token.encode(), name))
    if not entries:
        raise ConfigError(p, where, "no operator", _LINE)
    return Operators(p, tuple(entries))
