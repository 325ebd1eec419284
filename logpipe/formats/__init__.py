"""logpipe/formats."""
