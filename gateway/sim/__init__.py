"""Simulated Fischer 26E airframes speaking the real wire protocol."""
