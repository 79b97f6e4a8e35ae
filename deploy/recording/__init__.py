"""Recordings of runs: the recorder process (``agos record``, recorder), one episode as a rerun
file (episode) and the rerun viewer on one (``agos view``, view)."""
