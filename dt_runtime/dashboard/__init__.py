"""`dt dashboard`: the live cell in the browser, beside a running `dt run`.

It joins the cell's bus as one more peer (feed.BusFeed: the runtime YAML's `bus` section, TLS
and access control included), keeps the latest state and bounded histories (hub.Hub), knows the
twin itself (scene.Scene: kinematics, calibrated volume, Eq. 17 thresholds, provenance), and
serves one page with a live feed (server: Starlette on uvicorn, one guard, server-sent events;
the page's files in static/, a self-written canvas 3D view, nothing fetched at run time).
Operators (operators: a 0600 token file) may acknowledge a request or confirm maintenance done;
the server signs it with the bus key, under the operator's name. The cell's
view draws the twin's error map as arrows at its campaign's points (scene.error_map). A second
page, the metrologist's view (/metrology, `--results DIR`; results: what it reads of a compare,
diagnose or twin result), explores a result's residual map per point, filtered, with the diagnose
steps and the report's figures; without a runtime config it is served alone, no bus joined.
docs/dashboard.md tells how to run it and what each panel shows.
"""
