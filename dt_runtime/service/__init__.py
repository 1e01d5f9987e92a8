"""The twin in service: the daemon loop (`daemon`) and its parts, the target sources (`targets`),
the cell's drivers and clock (`cell`), escalation records, paging and operator actions
(`paging`), the counters health and summary read (`counters`), the housekeeping thread
(`housekeeping`); bounded corrections and Eq. 17 monitoring (`correction`), the escalation state
machine (`escalation`), the durable SQLite store (`store`), and the daemon's sides of the Zenoh
bus: the publisher over the store's outbox (`publisher`) and the correction server over the
corrector (`correction_server`). The Zenoh client itself is `dt_runtime.fabric`, below the daemon.
"""
