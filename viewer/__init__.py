"""Interactive viewer (installed as `fastenerf.viewer`)."""
