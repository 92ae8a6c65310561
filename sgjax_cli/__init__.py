"""The `sgjax` command line: the top of the house, above `train`, `eval`, `envs` and the `sgjax` library.

`main(argv)` parses one subcommand (`sgjax example | fit | objects | label | train | primitives |
match | plan | declutter`) and runs it; `sgjax_cli.commands` holds the subcommands, each importing
what it needs when it runs, so `sgjax --help` imports no simulator.
"""

from sgjax_cli.commands import build_parser, main

__all__ = ["build_parser", "main"]
