"""What every device on the line protocol shares: configuration into its frozen config and a
`SerialLink`, the handshake on activation (PING with the protocol version), and closing the
port on deactivation and close. The controller and the tracker add their own commands."""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar, Generic, TypeVar

from drivers.base import Abortable, Lifecycle
from drivers.serial import protocol as lp
from drivers.serial.link import LinkConfig, SerialLink, ack_fields
from dt_kernel.config import validate
from dt_kernel.errors import DriverError, StateError

C = TypeVar("C", bound=LinkConfig)


class SerialDevice(Abortable, Lifecycle, Generic[C]):
    """Base of the serial drivers: configure validates ``config_model`` and builds the SerialLink,
    activate opens the port and pings (the protocol version must match), deactivate and close
    close the port. Abortable: ``abort()`` ends the request in flight.
    """
    name: ClassVar[str]
    config_model: ClassVar[type[LinkConfig]]  # the device's config (a LinkConfig with its limits)

    def __init__(self, config: Mapping[str, Any] | None = None, source: str | None = None, *,
                 world: Any = None):  # world: unused, the registry passes it to every driver
        self._source = source or f"<{self.name} config>"
        self.cfg: C | None = None
        self.link: SerialLink | None = None
        if config is not None:
            self.configure(config)

    # --- configured parts (built by `configure`) ----------------------------------------
    @property
    def _link(self) -> SerialLink:
        if self.link is None:
            raise StateError(f"{self.name}: used before configure()")
        return self.link

    @property
    def _cfg(self) -> C:
        if self.cfg is None:
            raise StateError(f"{self.name}: used before configure()")
        return self.cfg

    # --- lifecycle hooks ----------------------------------------------------------------
    def _on_configure(self, config: dict[str, Any]) -> None:
        self.cfg = validate(self.config_model, config, self._source)  # type: ignore[assignment]  # C is config_model
        self.link = SerialLink(self._cfg, self.name, abort=self.abort_event)

    def _on_activate(self) -> None:
        self._link.open()
        try:
            self.ping()
        except DriverError:
            self._link.close()
            raise

    def _on_deactivate(self) -> None:
        self._link.close()

    def _on_close(self) -> None:
        if self.link is not None:
            self.link.close()

    def ping(self) -> str:
        """Handshake; returns the device name. Checks the protocol version."""
        f = ack_fields(self.name, "PING", self._link.request("PING"))
        if not f or f[0] != lp.PROTOCOL_VERSION:
            raise DriverError(f"{self.name}: protocol version {f[:1]} not supported (need {lp.PROTOCOL_VERSION})")
        return f[1] if len(f) > 1 else ""
