"""agos.world.towns: the offline town pipeline. Procedural street plans and OpenDRIVE maps become
one lane network, then a furnished layout, road graphs and the UAV grid, frozen as an asset whose
sha256 names it. Pure data and geometry: nothing here renders or simulates.

The flat modules are the road contract and the builders that freeze a town (``procedural``,
``imported``, ``asset``); the render style (``look``: meshes, textures, the rich city) is the
subpackage :mod:`agos.world.towns.look`, which the road contract never imports.
"""
