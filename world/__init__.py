"""agos.world: the simulated city.

``towns`` is the offline town pipeline (street plans, OpenDRIVE import, road graphs, UAV grid,
frozen assets); ``sim`` is the online simulation (the PyBullet scene, sensors, the CONFIRM checker,
the episode engine and the world worker process); ``episodes`` samples solvable episodes and
splits them. ``commands`` holds ``agos map`` and ``agos episodes``. Imports ``agos.runtime`` only.
"""
