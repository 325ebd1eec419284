"""Files and commits: atomic writes and Parquet/JSON IO, the artifact commit protocol (one writer per folder, one
manifest swap), whole-folder swaps for checkpoints, and the crash points the crash-injection tests kill at."""
