"""What every family's checkpoint shares (``format``): the format name and errors, the dataset kinds a checkpoint
fits, ``TrainingData``, ``InferenceSettings`` and the ``meta.json`` checksum that catches an edited file. Each family
writes and reads its own folder (``zhu2020.checkpoint`` / ``zhu2020.meta``, ``residual.checkpoint`` /
``residual.meta``; the social baselines through ``weights_folder``): weights in safetensors under their sha256,
never a pickle. The shipped weights live in
``model/checkpoints/`` (data, not code).

Imports: core (``logpipe/``) only; never a family.
"""
