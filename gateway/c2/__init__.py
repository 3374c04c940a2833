"""The C2 side: the sink contract, the sink runner, plugin discovery."""
