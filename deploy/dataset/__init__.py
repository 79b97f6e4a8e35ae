"""AGOS-Dataset (docs/DATASET.md): ``agos dataset build``, a run of the expert whose records are
assembled into episode directories (build), and ``agos dataset stats`` over what was built (stats)."""

DEFAULT_CAPTURE_EVERY_M = 10.0
"""A build's ``[world] capture_every_m`` unless told another (``agos dataset build --capture-every``)."""
