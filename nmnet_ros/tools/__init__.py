"""The ``nmnet`` command: one module per subcommand (replay, make-bag, eval, train, neighbors, bench, demo)."""
