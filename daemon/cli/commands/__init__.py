"""What the ``rumba`` subcommands do, one module each, imported by ``daemon.cli.parsers`` on use."""
