"""Data contracts as files: Arrow table schemas (*.json) and MCAP channel JSON Schemas (*.schema.json).

Installed as package data under ``logpipe.schemas``; load them with ``logpipe.contracts``.
"""
