"""The batch service: manifests, SQLite store, Ray scheduling and the CLI."""
