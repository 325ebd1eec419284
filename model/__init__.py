"""logpipe.model: the predictors, one package per family, and how a run picks one.

Packages (each ``__init__`` says what it holds and what it may import; ``docs/architecture.md`` §1 draws them and
``tests/test_architecture.py`` holds the rules):

* ``training``: what every family trains and runs with: devices, per-sample seeds, batch-invariant arithmetic
  (``row_blocks``), the best-of-H loss (eq. 23), DDP helpers, streaming scenes, the run folder's lock;
* ``checkpoint``: what every family's checkpoint shares: format, errors, dataset kinds, ``TrainingData``, inference
  settings, the ``meta.json`` checksum (the weights ship in ``model/checkpoints/``);
* ``kinematic``: constant velocity, least-squares CV, Kalman, the CV sampler, the adaptive prior;
* ``zhu2020``: the paper's network (Zhu et al., IJCAI 2020; also its LSTM and Noise-LSTM presets), one module per
  part, its training loop and checkpoints;
* ``residual``: our driving model, corrections to the adaptive kinematic prior (issue 57).
* ``social_lstm``, ``social_gan``: the comparison baselines Social-LSTM and Social-GAN (20V-20, 20VP-20), issue 63.

Modules at the top: ``predictor`` (the ``Predictor`` interface every method implements), ``registry`` (which
predictor a run uses: shipped checkpoints, baselines, inference settings), ``social`` (``logpipe train --preset
social_*``), ``ray_predict`` (forecasts on Ray or in worker processes) and ``synthetic`` (synthetic scenes for
tests and benchmarks).

Layers inside ``model/``: ``training`` < ``checkpoint``, ``kinematic`` < the families < the top modules. A family
imports ``training``, ``checkpoint`` and ``kinematic``, never another family; ``training``, ``checkpoint`` and
``kinematic`` import no family. Submodules are imported on demand so that importing the package stays cheap.
"""
