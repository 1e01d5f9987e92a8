"""The plant: many cells (one twin daemon per robot) on one Zenoh fabric (docs/plant.md).

Each cell keeps its own store (the embedded default) and its bus (`fabric`); the plant sees
every cell through one or more Zenoh routers:

- `config`: the plant config (`PlantConfig`: the router's endpoints and access control, how the
  plant's tools join the fabric, the cells expected, the history database), validated once.
- `router`: `dt router`, a Zenoh session in router mode (the library the bus already uses).
- `status`: one query on `dt/<cell>/<robot>/<kind>` collects every cell's answer (the cells
  serve them: `fabric.queries`), and names the expected cells that did not answer.
- `history`: the plant's record of every maintenance request received (SQLite by default,
  PostgreSQL when configured), one row per request (uid) and consumer group.
- `inbox`: the plant's maintenance inbox: a `MaintenanceConsumer` whose requests land in the
  history before they are acknowledged.
"""
