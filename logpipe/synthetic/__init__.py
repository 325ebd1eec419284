"""Synthetic data generators. Everything they write is labelled synthetic (file names, log ids, READMEs)."""
