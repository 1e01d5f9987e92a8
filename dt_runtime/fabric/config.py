"""Bus configuration: endpoints, TLS and access control, validated once; their zenoh mapping.

Config (`BusConfig`, configs/bus.yaml) maps onto the zenoh JSON5 config as:
    mode                  -> mode ("peer" | "client")
    listen, connect       -> listen/endpoints, connect/endpoints
    multicast_scouting    -> scouting/multicast/enabled (default false: loopback tests stay local)
    gossip_scouting       -> scouting/gossip/enabled
    tls.root_ca_certificate, listen_certificate, listen_private_key, connect_certificate,
    connect_private_key, enable_mtls, verify_name_on_connect
                          -> transport/link/tls/<same name>   (endpoints must use tls/ or quic/)
    access_control.enabled, default_permission, rules[], subjects[], policies[]
                          -> access_control/<same name> (zenoh 1.x ACL schema: rules have id,
                             messages, flows, permission, key_exprs; subjects id plus
                             interfaces / cert_common_names / usernames / zids; policies
                             reference rule and subject ids, checked here)
    extra                 -> any further zenoh key path -> JSON value (escape hatch)
    auth.key_file, auth.max_age_s
                          -> not zenoh's: the key that signs maintenance messages (bus.auth)
configs/bus_tls_acl_example.yaml shows TLS + ACL.
Invalid values raise ConfigError through dt_kernel.config (naming the key); a value zenoh
itself rejects raises BusError.
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
    """`k` if zenoh accepts it as a key expression; ValueError (for the validators) if not."""
    try:
        with zenoh_errors(f"invalid zenoh key expression {k!r}"):
            zenoh.KeyExpr(k)
    except BusError as exc:
        raise ValueError(str(exc)) from exc
    return k


def check_endpoint(e: str) -> str:
    proto, sep, rest = e.partition("/")
    if not sep or not rest or proto not in ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream"):
        raise ValueError(f"endpoint {e!r} must look like tcp/127.0.0.1:7447 "
                         "(protocols tcp, udp, tls, quic, ws, unixsock-stream)")
    return e


class TlsConfig(Frozen):
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
    id: str
    interfaces: list[str] | None = None
    cert_common_names: list[str] | None = None
    usernames: list[str] | None = None
    zids: list[str] | None = None


class AclPolicy(Frozen):
    id: str | None = None
    rules: list[str]
    subjects: list[str]


class AccessControlConfig(Frozen):
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
        return f"dt/{self.cell}/{self.robot}/{kind}"

    def zenoh_config(self) -> zenoh.Config:
        """The zenoh.Config this maps to (see the module docstring)."""
        return zenoh_config(self.mode, self.listen if self.mode == "peer" else [], self.connect,
                            self.multicast_scouting, self.gossip_scouting, self.tls, self.access_control, self.extra)


def zenoh_config(mode: str, listen: list[str], connect: list[str], multicast_scouting: bool, gossip_scouting: bool,
                 tls: TlsConfig | None, access_control: AccessControlConfig | None,
                 extra: dict[str, Any]) -> zenoh.Config:
    """The zenoh.Config of a node (a bus peer or client, or the plant's router: dt_runtime.plant)."""
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
    return load_yaml(path, BusConfig)
