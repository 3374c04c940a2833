"""Shared transports: the bounded TCP listener, TLS contexts."""
