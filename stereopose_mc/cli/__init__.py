"""The ``spmc`` command line: thin typer commands, each calling one typed function."""
