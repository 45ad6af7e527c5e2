"""Subcommands of the `mlaqc` CLI, one module each (see mlaqc.cli)."""
