"""logpipe.model: the Zhu et al. (IJCAI 2020) multi-agent trajectory predictor and its baselines.

Entry points for the stages:

* ``config``: ``ModelConfig`` / ``TrainConfig`` (every hyper-parameter, JSON/TOML files, Table 4 presets);
* ``training.fit(train, val, config, out_dir, resume=..., progress=..., dataset_kind=..., manifest_hash=...)``;
* ``checkpoints.load_checkpoint(path, expect_kind=..., expect_config=...)``;
* ``predictor.Predictor`` (``predict(samples, num_modes, seed)``), implemented by ``predictor.NetPredictor``
  (the paper's network, LSTM and Noise-LSTM presets) and the classical ``baselines``.

Submodules are imported on demand (``from logpipe.model.training import fit``) so that importing the
package stays cheap.
"""
