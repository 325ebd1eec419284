"""What every predictor family trains and runs with, whatever its network.

* ``device``: ``--device auto|cpu|cuda`` and the mixed precision that goes with CUDA;
* ``seeding``: per-sample random streams; ``row_blocks``: arithmetic whose result for one agent never depends on its
  batch mates (together: a forecast depends only on checkpoint, settings, seed and sample);
* ``loss``: the best-of-H loss (eq. 23 of Zhu et al.; Social-GAN's variety loss is the same) and displacement errors;
* ``data_parallel``: DDP under ``torchrun``; ``scene_stream``: a ``DataLoader`` over a dataset's shards;
  ``splits``: a split's logs in several datasets;
  ``run_folder``: a training run's folder lock, device and chained sample streams.
* ``social_batch`` (windows of whole tracks stacked, with their within-window pairs), ``window_loop`` (the social
  baselines' training loop) and ``config_table`` (a family's settings from a TOML table).

Imports: core (``logpipe/``) and torch only; never a family, ``checkpoint``, ``kinematic`` or the top modules.
"""
