"""AGOS-Dataset (docs/DATASET.md): ``agos dataset build``, a run of the expert whose records are
assembled into episode directories (build), and ``agos dataset stats`` over what was built (stats)."""
