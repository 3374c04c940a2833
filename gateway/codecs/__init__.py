"""Wire formats shared by sinks and sources."""
