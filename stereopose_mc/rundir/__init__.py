"""The run directory as storage: table columns and units, chunks and sidecars, integrity, lock, manifest."""
