"""The rumba command line: main.py dispatches to one module per subcommand in commands/."""
