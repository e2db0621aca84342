"""Small helpers with no domain knowledge: atomic file writes, CLIs generated from config dataclasses."""
