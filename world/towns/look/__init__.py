"""agos.world.towns.look: how a town is drawn, the render style (``look``: ``flat`` boxes or the
``rich`` textured city), kept apart from what the town *is* (lanes, layout, road graphs, UAV grid).

Surface and deck meshes (``meshes``), textured meshes and shapes (``texmesh``), generated textures
(``textures``), the street level (``streetdressing``), buildings and skyline (``facades``), trees
and lamp posts (``furniture``), shadows as geometry (``shadows``), vehicle meshes (``vehicles``),
the city the scene turns into bodies (``city``), and the drawing of a town's dressing
(``decorate``; the frozen choices themselves, :mod:`agos.world.towns.dressing`, are data the layout
carries and the asset hashes). Pure numpy: only ``world/sim/scene.py`` hands any of it to PyBullet.

The road contract never imports this package (an import-linter contract in pyproject.toml): a change
to the look cannot move a lane, a road graph, the UAV grid or a placement.
"""
