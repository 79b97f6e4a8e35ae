"""agos.agents.human: the Human reference. An agent service whose policy is a person at a browser.

``agos human --role uav|ugv|both`` serves a page (``server``) that shows exactly what the role's
agent receives (``page_model``: the images AGOS-Agent's prompt carries, the map, the references, the
legal choices, the coordination state, the budget), takes the person's choice through a board
that accepts each decision once and only when it is legal (``board``), and answers it on the bus
like any agent service (``human_service``). The same page is a read-only spectator of the visualisation
stream (``spectator``). Imports ``agos.runtime`` and ``agos.agents`` only.
"""
