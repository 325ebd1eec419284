"""The residual driving model, our extension (issue 57): learned corrections to the adaptive kinematic prior
(``model.kinematic.adaptive_prior``), read in each target's own frame; ``logpipe predict``'s default on driving data.

* ``config`` (``ResidualConfig``, the ``[residual]`` TOML table), ``inputs`` (each target in its own frame: track,
  neighbours, map crop), ``net`` (``ResidualNet``: mean head for K = 1, scored mode heads), ``modes`` (which of
  them make the K modes), ``fit`` (training), ``run`` (``logpipe train`` with a ``[residual]`` config), ``fleet``
  (``logpipe train`` on driving data without a config: the shipped model's recipe, its own validation data,
  fine-tuned or from scratch), ``compare`` (against the kinematic baselines on held-out targets), ``model_card``
  (the run's ``MODEL_CARD.md``), ``meta`` and ``checkpoint`` (its folder), ``ood`` (the training distribution,
  out-of-distribution scores and the fallback), ``predictor`` (``ResidualPredictor``).

What it shares with the paper's network (``model.zhu2020``) is the role of its parts, not code: the target encoder
plays LSTM_E's role, the neighbour max-pool the AIN's position feature (eqs. 1-2), the map-crop CNN the EN's
(eqs. 11-12). Imports: core, ``model.training``, ``model.checkpoint``, ``model.kinematic``; never another family.
"""
