"""A real PostgreSQL server for the plant-history tests, from the `pgserver` wheel (its binaries
ship inside the package: nothing from apt, no mock). Started in a fresh directory, stopped and
deleted at the end. As root (CI), pgserver runs the server as its own system user `pgserver`
(PostgreSQL refuses root) and opens the data directory's parents for traversal: so the directory
is a new one under the system's temporary directory, not pytest's private tree."""
from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def postgres_server() -> Iterator[str]:
    """A running server; yields its connection URL (a Unix socket in the data directory)."""
    import pgserver

    root = Path(tempfile.mkdtemp(prefix="dt-pg-"))
    srv = pgserver.get_server(root / "pgdata", cleanup_mode="delete")
    try:
        yield srv.get_uri()
    finally:
        srv.cleanup()
        shutil.rmtree(root, ignore_errors=True)
