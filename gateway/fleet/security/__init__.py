"""Link security: the AES-256-GCM tunnel, MAVLink 2 signing, key material."""
