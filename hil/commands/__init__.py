"""Subcommands of the `hil` command line, one module each."""
