"""Localisation-error profiles (TOML), shipped as package data: ``--pose-error NAME``."""
