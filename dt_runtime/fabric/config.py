"""Bus configuration (`BusConfig`, configs/bus.yaml): endpoints, TLS, access control and the
signing key, validated once, and the zenoh configuration they map onto (`zenoh_config`).

The keys, their defaults and their zenoh paths: docs/bus.md ("Configuration"; TLS and access
control: configs/bus_tls_acl_example.yaml). An invalid value raises ConfigError through
dt_kernel.config, naming the key; a value zenoh itself rejects raises BusError.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal

import zenoh
from pydantic import Field, field_validator, model_validator

from dt_kernel.config import Frozen, load_yaml
from dt_runtime.fabric.auth import AuthConfig
from dt_runtime.fabric.session import BusError, zenoh_errors

#: The largest maintenance request, ack or done taken off the bus (they are a few hundred bytes):
#: a bigger one is refused as malformed before it is parsed.
MAX_MESSAGE_BYTES = 64 * 1024

ACL_MESSAGES = ("put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                "liveliness_token", "liveliness_query", "declare_liveliness_subscriber")


def keyexpr_ok(k: str) -> str:
    """`k` if zenoh accepts it as a key expression; ValueError (for the validators) if not.

    Parameters
    ----------
    k : str
        A key expression, e.g. `dt/*/*/maintenance/**`.

    Returns
    -------
    str
        `k`, unchanged.

    Raises
    ------
    ValueError
        Zenoh refuses `k` (its message).
    """
    try:
        with zenoh_errors(f"invalid zenoh key expression {k!r}"):
            zenoh.KeyExpr(k)
    except BusError as exc:
        raise ValueError(str(exc)) from exc
    return k


def check_endpoint(e: str) -> str:
    """`e` if it looks like a zenoh endpoint `<protocol>/<address>`; ValueError (for the validators)
    if not. Only the form is checked: zenoh parses the address when the session opens.

    Parameters
    ----------
    e : str
        An endpoint, e.g. `tcp/127.0.0.1:7447`; protocols tcp, udp, tls, quic, ws,
        unixsock-stream.

    Returns
    -------
    str
        `e`, unchanged.

    Raises
    ------
    ValueError
        No protocol, another protocol, or nothing after the `/`.
    """
    proto, sep, rest = e.partition("/")
    if not sep or not rest or proto not in ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream"):
        raise ValueError(f"endpoint {e!r} must look like tcp/127.0.0.1:7447 "
                         "(protocols tcp, udp, tls, quic, ws, unixsock-stream)")
    return e


class TlsConfig(Frozen):
    """`bus.tls`: zenoh's `transport/link/tls/*`, one key each (docs/bus.md, "Beyond loopback").

    `root_ca_certificate`: the plant CA's certificate (PEM path). `listen_certificate`,
    `listen_private_key`: what this node shows to peers connecting to it; `connect_certificate`,
    `connect_private_key`: what it shows when it connects (each pair given together or not at all).
    `enable_mtls`: require peers' certificates (needs the connect pair). `verify_name_on_connect`:
    check the peer's certificate names the host connected to.
    """

    root_ca_certificate: str
    listen_certificate: str | None = None
    listen_private_key: str | None = None
    connect_certificate: str | None = None
    connect_private_key: str | None = None
    enable_mtls: bool = False
    verify_name_on_connect: bool = True

    @model_validator(mode="after")
    def _pairs(self) -> TlsConfig:
        for side in ("listen", "connect"):
            cert, key = getattr(self, f"{side}_certificate"), getattr(self, f"{side}_private_key")
            if (cert is None) != (key is None):
                raise ValueError(f"{side}_certificate and {side}_private_key go together")
        if self.enable_mtls and self.connect_certificate is None:
            raise ValueError("enable_mtls needs connect_certificate/connect_private_key")
        return self


class AclRule(Frozen):
    """One rule of zenoh 1.x access control: `id`; the `messages` it covers (`ACL_MESSAGES`);
    `flows` (ingress, egress; default both); `permission` (allow or deny); `key_exprs` (checked
    to be valid key expressions), which must include a message's key for the rule to apply."""

    id: str
    messages: list[Literal[ACL_MESSAGES]]  # type: ignore[valid-type]
    flows: list[Literal["ingress", "egress"]] = ["ingress", "egress"]
    permission: Literal["allow", "deny"]
    key_exprs: list[str]

    @field_validator("key_exprs")
    @classmethod
    def _k(cls, v: list[str]) -> list[str]:
        return [keyexpr_ok(k) for k in v]


class AclSubject(Frozen):
    """Who a policy applies to: `id`, and any of `interfaces`, `cert_common_names` (TLS
    certificates' CN), `usernames`, `zids` (zenoh ids)."""

    id: str
    interfaces: list[str] | None = None
    cert_common_names: list[str] | None = None
    usernames: list[str] | None = None
    zids: list[str] | None = None


class AclPolicy(Frozen):
    """Applies the `rules` (ids) to the `subjects` (ids); `id` is optional."""

    id: str | None = None
    rules: list[str]
    subjects: list[str]


class AccessControlConfig(Frozen):
    """`bus.access_control`: zenoh 1.x's `access_control`, one key each.

    `enabled` (default true); `default_permission` for messages no rule covers (default deny);
    `rules`, `subjects` and `policies`. A policy naming a rule or subject that is not defined is
    refused when the config is loaded.
    """

    enabled: bool = True
    default_permission: Literal["allow", "deny"] = "deny"
    rules: list[AclRule] = []
    subjects: list[AclSubject] = []
    policies: list[AclPolicy] = []

    @model_validator(mode="after")
    def _refs(self) -> AccessControlConfig:
        rules, subjects = {r.id for r in self.rules}, {s.id for s in self.subjects}
        for p in self.policies:
            for r in p.rules:
                if r not in rules:
                    raise ValueError(f"policy refers to unknown rule {r!r}; rules: {sorted(rules)}")
            for s in p.subjects:
                if s not in subjects:
                    raise ValueError(f"policy refers to unknown subject {s!r}; "
                                     f"subjects: {sorted(subjects)}")
        return self


class BusConfig(Frozen):
    """The `bus:` section of the runtime config, or configs/bus.yaml (docs/bus.md, "Configuration").

    `cell`, `robot`: the key prefix `dt/<cell>/<robot>` (one key chunk each: no `/ * $ ? #`).
    `mode`: peer or client (a client needs `connect`, a router). `listen`, `connect`: endpoints
    (`listen` is used in peer mode only). `multicast_scouting`, `gossip_scouting`: zenoh
    discovery. `consumer_groups`: 1 to 16 distinct groups, each receiving its own copy of every
    maintenance request. `health_period_s`, `republish_period_s`, `close_timeout_s`: s.
    `send_queue`: reliable messages waiting for the worker. `tls`, `access_control`: see their
    classes (TLS needs a `tls/` or `quic/` endpoint). `auth`: the signing key (`AuthConfig`).
    `extra`: further zenoh config paths -> JSON values, applied last.
    """

    cell: str = "cell1"
    robot: str = "r1"
    mode: Literal["peer", "client"] = "peer"
    listen: list[str] = ["tcp/127.0.0.1:0"]
    connect: list[str] = []
    multicast_scouting: bool = False
    gossip_scouting: bool = True
    # Every group receives its own copy of each maintenance request (its own outbox row, id and
    # acknowledgement): a maintenance system and, say, the plant's MES each get every request,
    # instead of the first acker taking it for everyone. A consumer says which group it is.
    consumer_groups: list[str] = Field(["maintenance"], min_length=1, max_length=16)
    health_period_s: float = Field(1.0, gt=0, le=3600)  # `.../health` is also sent on every change
    republish_period_s: float = Field(2.0, gt=0)
    close_timeout_s: float = Field(3.0, gt=0)
    send_queue: int = Field(1000, ge=1)
    tls: TlsConfig | None = None
    access_control: AccessControlConfig | None = None
    # The key that signs maintenance requests, acks and dones (bus.auth; docs/bus.md): always on.
    auth: AuthConfig = AuthConfig()
    extra: dict[str, Any] = {}

    @field_validator("cell", "robot")
    @classmethod
    def _chunk(cls, v: str) -> str:
        if not v or any(c in v for c in "/*$?#"):
            raise ValueError(f"{v!r} must be one non-empty key chunk (no / * $ ? #)")
        return v

    @field_validator("consumer_groups")
    @classmethod
    def _groups(cls, v: list[str]) -> list[str]:
        for g in v:
            cls._chunk(g)
        if len(set(v)) != len(v):
            raise ValueError(f"consumer_groups {v} name a group twice")
        return v

    @field_validator("listen", "connect")
    @classmethod
    def _eps(cls, v: list[str]) -> list[str]:
        return [check_endpoint(e) for e in v]

    @model_validator(mode="after")
    def _tls_endpoints(self) -> BusConfig:
        if self.tls is not None:
            eps = self.listen + self.connect
            if not any(e.startswith(("tls/", "quic/")) for e in eps):
                raise ValueError("tls is configured but no listen/connect endpoint uses tls/ "
                                 "or quic/")
        if self.mode == "client" and not self.connect:
            raise ValueError("mode 'client' needs at least one connect endpoint (a router)")
        return self

    def key(self, kind: str) -> str:
        """The key expression of this robot's `kind`.

        Parameters
        ----------
        kind : str
            What follows the prefix, e.g. `health`, `correct` or `maintenance/request`.

        Returns
        -------
        str
            `dt/<cell>/<robot>/<kind>`.
        """
        return f"dt/{self.cell}/{self.robot}/{kind}"

    def zenoh_config(self) -> zenoh.Config:
        """The zenoh.Config this maps to (docs/bus.md, "Configuration"): `listen` only in peer mode.

        Raises
        ------
        BusError
            Zenoh rejects a value.
        """
        return zenoh_config(self.mode, self.listen if self.mode == "peer" else [], self.connect,
                            self.multicast_scouting, self.gossip_scouting, self.tls, self.access_control, self.extra)


def zenoh_config(mode: str, listen: list[str], connect: list[str], multicast_scouting: bool, gossip_scouting: bool,
                 tls: TlsConfig | None, access_control: AccessControlConfig | None,
                 extra: dict[str, Any]) -> zenoh.Config:
    """The zenoh.Config of a node (a bus peer or client, or the plant's router: dt_runtime.plant).

    Parameters
    ----------
    mode : str
        Zenoh's `mode`: `peer`, `client` or `router`.
    listen, connect : list of str
        Endpoints (`listen/endpoints`, `connect/endpoints`).
    multicast_scouting, gossip_scouting : bool
        `scouting/multicast/enabled`, `scouting/gossip/enabled`.
    tls : TlsConfig or None
        Each key given goes to `transport/link/tls/<key>`.
    access_control : AccessControlConfig or None
        Goes to `access_control`.
    extra : dict of str to JSON values
        Further zenoh config paths, inserted last (they override the above).

    Returns
    -------
    zenoh.Config

    Raises
    ------
    BusError
        Zenoh rejects a value.
    """
    with zenoh_errors("zenoh rejected the bus config"):
        c = zenoh.Config()
        c.insert_json5("mode", json.dumps(mode))
        c.insert_json5("listen/endpoints", json.dumps(listen))
        c.insert_json5("connect/endpoints", json.dumps(connect))
        c.insert_json5("scouting/multicast/enabled", json.dumps(multicast_scouting))
        c.insert_json5("scouting/gossip/enabled", json.dumps(gossip_scouting))
        if tls is not None:
            for k, v in tls.model_dump(exclude_none=True).items():
                c.insert_json5(f"transport/link/tls/{k}", json.dumps(v))
        if access_control is not None:
            c.insert_json5("access_control", json.dumps(access_control.model_dump(exclude_none=True)))
        for k, v in extra.items():
            c.insert_json5(k, json.dumps(v))
    return c


def load_bus_config(path: str | Path) -> BusConfig:
    """Read and validate a bus config file.

    Parameters
    ----------
    path : str or Path
        A YAML file of `BusConfig`'s keys, e.g. configs/bus.yaml.

    Returns
    -------
    BusConfig

    Raises
    ------
    ConfigError
        Naming the file and key, when the file cannot be read or a value is invalid.
    """
    return load_yaml(path, BusConfig)
