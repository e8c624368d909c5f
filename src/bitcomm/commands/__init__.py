"""Subcommands of the `bitcomm` CLI, one module each (found by name by `bitcomm.cli`).

The top layer: may import every package. Building the parsers must not import torch (`bitcomm --help`
stays fast), so a command imports what it runs inside its `run(args)`.
"""
