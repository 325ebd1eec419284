"""MCAP and Foxglove output: ingest's per-log MCAP of the tracks, copying a recording unchanged while appending
channels, Foxglove Protobuf messages (scene updates of forecasts, raster images) built from pre-serialised parts."""
