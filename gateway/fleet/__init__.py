"""The airframe side: links and their security, MAVLink intake, normalising, link health,
the passthrough, the commander; ``fleet.Fleet`` builds and runs them all and owns the uplink.
"""
