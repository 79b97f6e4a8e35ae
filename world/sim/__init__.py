"""agos.world.sim: the online simulation of one episode at a time. The PyBullet scene (the only
module importing pybullet), cameras, the CONFIRM checker, waypoint options, the coordination
channel, the episode engine on its event-driven clock, and the world worker process.
"""
