"""The spool: durable events held in SQLite until each sink confirms them (``store``)."""
