"""The fabric: the Zenoh client every part of a plant uses (a cell's daemon, the plant's router,
inbox and status, the dashboard, `dt ack` / `dt consume`). It imports nothing of the daemon
(service/), the twin or its models: opening a session or reading a bus config loads no GP.

- `config`: `BusConfig` (endpoints, TLS, access control, signing key), validated once, and its
  zenoh configuration.
- `session`: the one place where zenoh errors become `BusError`; session open (`SessionOpener`
  for a client whose router is not up yet) and bounded close; JSON payloads.
- `auth`: the service's key; maintenance requests, acks and dones are signed, unsigned ones refused.
- `consumer`: `MaintenanceConsumer`, which takes, de-duplicates and acknowledges requests.
- `queries`: `QueryServer`, the request-reply answers a cell serves.
- `correction_client`: `request_correction`, a program's side of `.../correct`.

The daemon's own sides live with the daemon (`service.publisher.Bus`, `service.correction_server`).
The keys, their delivery, the maintenance protocol and who can do what: docs/bus.md.
"""
from __future__ import annotations

from dt_runtime.fabric.config import (
    AccessControlConfig,
    AclPolicy,
    AclRule,
    AclSubject,
    BusConfig,
    TlsConfig,
    load_bus_config,
)
from dt_runtime.fabric.consumer import MaintenanceConsumer
from dt_runtime.fabric.session import BusError, close_session, open_session

_open = open_session  # the name tests/integration/test_bus.py imports

__all__ = ["AccessControlConfig", "AclPolicy", "AclRule", "AclSubject", "BusConfig", "BusError",
           "MaintenanceConsumer", "TlsConfig", "close_session", "load_bus_config", "open_session"]
