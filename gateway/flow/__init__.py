"""The middle: the bus that routes events to subscribers."""
