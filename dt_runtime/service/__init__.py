"""The twin in service: the daemon loop (`daemon`), bounded corrections and Eq. 17 monitoring
(`correction`), the escalation state machine (`escalation`), the durable SQLite store (`store`)
and the Zenoh bus (`bus`).
"""
