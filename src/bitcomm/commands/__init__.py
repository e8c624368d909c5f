"""Subcommands of the `bitcomm` CLI, one module each."""
