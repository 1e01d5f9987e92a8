"""Re-export of the project's exception hierarchy (defined in sim.errors, the lowest layer)."""
from sim.errors import (  # noqa: F401
    ConfigError,
    DataError,
    DriverError,
    ModelError,
    StateError,
    TwinError,
    UnreachableError,
)
