"""The airframe side: links and their security, MAVLink intake, normalising, link health,
the passthrough.
"""
