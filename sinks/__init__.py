"""Output sinks of fischer-gateway, one module per output system."""
