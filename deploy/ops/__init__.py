"""Operating a bus: a CA and per-identity certificates for a secured bus (``agos certs``, certs)
and the liveliness healthcheck the compose files run (``agos health``, healthcheck)."""
