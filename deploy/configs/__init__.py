"""Embedded run configurations and episode lists, shipped as package data."""
