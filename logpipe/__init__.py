"""logpipe."""
