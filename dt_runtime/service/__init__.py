"""The twin in service (`dt run`): the daemon loop (`daemon`) and its parts, the target sources
(`targets`), the cell's drivers and clock (`cell`), a streamed path program (`path_run`,
`stream`), the halt / trust policy (`supervisor`), escalation records, paging and operator
actions (`paging`), the escalation state machine (`escalation`), the durable SQLite store
(`store`, `rows`), `.../health` and the status view (`health`, `answers`), the counters
(`counters`), the housekeeping thread (`housekeeping`), and the daemon's sides of the Zenoh bus:
the publisher over the store's outbox (`publisher`) and the correction server (`correction_server`).
The correction law, its bounds and the Eq. 17 monitor are the twin's (`dt_runtime.twin`); the Zenoh
client is `dt_runtime.fabric`, below the daemon. The module map: docs/service.md ("Inside the daemon").
"""
