"""The fabric: the Zenoh client every part of a plant uses (a cell's daemon, the plant's router,
inbox and status, the dashboard, `dt ack` / `dt consume`). It imports nothing of the daemon
(service/), the twin or its models: opening a session or reading a bus config loads no GP.

The bus it speaks: telemetry, corrections, state and durable maintenance requests.

Key expressions (payloads are UTF-8 JSON objects, encoding application/json)::

    dt/<cell>/<robot>/telemetry                  best effort, CongestionControl.DROP, DATA_LOW
    dt/<cell>/<robot>/correction                 RELIABLE, BLOCK, DATA_HIGH
    dt/<cell>/<robot>/state                      RELIABLE, BLOCK, INTERACTIVE_HIGH
    dt/<cell>/<robot>/maintenance/request        RELIABLE, BLOCK, INTERACTIVE_HIGH
    dt/<cell>/<robot>/maintenance/ack/<id>       RELIABLE, BLOCK, INTERACTIVE_HIGH (consumer ->)

Delivery of maintenance requests (at least once, end to end):
1. `request_maintenance(payload)` writes the request to the Store outbox and commits it
   (fsync) BEFORE anything is published; a failing store raises StoreError and nothing is sent.
2. A worker thread publishes every pending outbox entry at once and then every
   `republish_period_s` until an ack arrives; a new Bus on the same Store (daemon restart)
   republishes whatever is still pending.
3. The consumer acks every copy it receives by publishing on `.../maintenance/ack/<id>` with
   `{"id", "uid", "t"}`, signed (`auth`); the Bus marks the outbox row acked only if the
   signature is the service's and the uid matches (ids restart if
   a store file is replaced; the uuid makes the pair unambiguous). Consumers de-duplicate on
   (cell, robot, uid).
Why a pub/sub ack and not a queryable/get: the request must survive the consumer being absent
for hours; with pub/sub the publisher never waits on a reply (no get timeouts in the loop), acks
and republishes are both idempotent, and a lost ack is repaired by the next republish.

Threads: zenoh callbacks only enqueue (never block, never touch SQLite). One worker thread
publishes reliable messages (so a BLOCK put never stalls the caller's control loop), handles
acks and republishes. Telemetry is put directly with DROP: it never blocks. The queue of
reliable messages is bounded (`send_queue`); when full, corrections/state are dropped and
counted in `dropped` (maintenance requests are never lost: they live in the outbox).
`close()` stops the worker and closes the session in a helper thread joined with a time-out.

Modules: `config` (BusConfig: endpoints, TLS and access control, validated once, and their
zenoh mapping), `session` (the one place where zenoh errors become BusError, session open and
bounded close, JSON payloads), `auth` (the service's key: requests, acks and dones are signed,
unsigned ones refused), `consumer` (MaintenanceConsumer), `queries` (QueryServer: the
request-reply answers a cell serves). The daemon's own sides live with the daemon:
`service.publisher` (Bus, over the store's outbox) and `service.correction_server`
(CorrectionServer and request_correction, over the twin's corrector).
TLS and access control: configs/bus_tls_acl_example.yaml. Who can do what: docs/bus.md.
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

_open = open_session  # the name tests and older callers use

__all__ = ["AccessControlConfig", "AclPolicy", "AclRule", "AclSubject", "BusConfig", "BusError",
           "MaintenanceConsumer", "TlsConfig", "close_session", "load_bus_config", "open_session"]
