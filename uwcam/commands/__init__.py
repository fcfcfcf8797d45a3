"""The command line's subcommands, one module per family; uwcam/cli.py builds the parser (docs/architecture.md)."""
