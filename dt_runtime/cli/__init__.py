"""The `dt` command line (the top layer): one module per command with its arguments, its run
and its human text; `main` assembles them. Entry point: `dt = dt_runtime.cli.main:main`."""
