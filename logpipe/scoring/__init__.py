"""Scoring: one method's forecasts as score reads them, which agents count and their true futures, ADE/FDE,
best-of-K and miss-rate metrics, the report folder and its plots."""
