"""Input plugins of fischer-gateway (entry-point group fischer_gateway.sources)."""
