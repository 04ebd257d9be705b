"""The ``archer`` command line: one module per command (``main`` dispatches)."""
