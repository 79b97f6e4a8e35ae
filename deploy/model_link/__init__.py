"""Placements of the model (TOML), shipped as package data: ``--model-link NAME`` (runtime/model_link.py)."""
