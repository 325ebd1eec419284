"""The reproduction scripts: each ``scripts/<name>.py`` with a ``main`` runs as ``python -m scripts.<name>`` from the
repository root (``reproduce_ethucy``, ``reproduce_apolloscape``, ``reproduce_argoverse``, ``reproduce_driving``,
``subset_check``, ``synthetic_map_check``, ``model_card``) and writes its results file in ``docs/results/`` (the
model cards in ``model/checkpoints/<kind>/``).

What several scripts share lives in one module per concept: ``locations`` (the repository, shipped and extra-seed
checkpoints, ingested datasets), ``validation`` (best-of-K errors and the settings chosen on validation),
``forecasts`` (each method's predictions files), ``seeds`` (the extra training seeds and their table) and ``tables``
(the Markdown pieces every results file shares). ``ethucy_checks`` and ``ethucy_report`` hold the ETH/UCY
reproduction's checks and its results file.
"""
