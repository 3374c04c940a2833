"""fischer-gateway: binds the Fischer 26E fleet to C2 systems."""
