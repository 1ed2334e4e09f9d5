"""shade."""
