"""camo evaluation: rendered views, image metrics (``evaluation.metrics``), benchmark tables and reports."""
