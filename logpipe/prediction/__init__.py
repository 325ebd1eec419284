"""Prediction runs: options and summary, sample rows → model inputs, the predictions table and its run folder, the
background shard writer, where a log's original recording is and the per-log MCAP of recording + forecasts."""
