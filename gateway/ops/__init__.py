"""Operating the daemon: health endpoint, metrics, systemd notify, logging, shipped files."""
