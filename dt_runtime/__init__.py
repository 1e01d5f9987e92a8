"""The digital twin: registration, plans, error models, uncertainty, runtime and CLI."""
