"""``archer bench SUBJECT``: one module per measured subject (``main`` dispatches)."""
