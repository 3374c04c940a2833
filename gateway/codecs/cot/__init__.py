"""Cursor-on-Target: building, encoding, parsing and validating events."""
