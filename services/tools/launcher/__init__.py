"""The `falconry` command: one module per subcommand (`*_cmd.py`), the run it plans and supervises."""
