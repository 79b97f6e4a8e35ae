"""Figures from a run's records: ``agos plot`` (plot), the records it reads (plot_data) and the
town map around an episode that figures and recordings draw on (episode_map)."""
