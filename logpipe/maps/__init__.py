"""logpipe/maps."""
