"""agos.world.episodes: offline episode sampling per difficulty, the solvability check by
rendering, and train/val/test splits.
"""
