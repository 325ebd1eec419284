"""The paper's network, Zhu et al. (IJCAI 2020), one module per part, named after the paper:

* ``interaction``: the Agent Interaction Network (eqs. 1-10); ``environment`` and ``backbone``: the Environment
  Network (ResNet18 stages 1-2 + ROIAlign, eqs. 11-12);
* ``layers``: every layer's parameters (the checkpoints' state_dict keys); ``encoder``: attention and LSTM_E
  (eqs. 13-16); ``decoder``: LSTM_D with noise (eqs. 17-22) and the ``Decoder`` interface that training and
  inference share; ``fast_decoder``: the same decoder for inference; ``network``: ``TrajectoryNet``, the noise z;
* ``config`` (``ModelConfig``, ``TrainConfig``, the Table 4 presets: LSTM and Noise-LSTM are presets of this
  network), ``batching`` (scenes to padded tensors in the model frame);
* training: ``fit`` (the loop), ``step_loss`` (eq. 23 per batch), ``evaluation``, ``train_config``,
  ``train_inputs``, ``feature_cache``; checkpoints: ``checkpoint`` (the folder), ``meta`` (its ``meta.json``);
  inference: ``predictor`` (``NetPredictor``).

Imports: core, ``model.training``, ``model.checkpoint`` (and ``model.kinematic``); never another family.
"""
