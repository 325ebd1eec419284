"""The on-disk dataset ingest writes and every later stage reads: the reader and writer, the logs table, the track
shards, the sample index, the one windowing implementation, ``--filter`` and resampling to the dataset's rate."""
