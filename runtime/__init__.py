"""agos.runtime: the floor every other package stands on.

The zenoh key space (``keys``), the wire messages (``schemas``) and their msgpack codec, the bus
(``bus``: zenoh sessions and an in-memory fake), link models, settings types and the episode
configuration, process helpers, the embedded router, observers, and pure camera and planar
geometry. Nothing here imports ``agos.world``, ``agos.agents``, ``agos.evaluator`` or ``agos.deploy``.
"""
