"""agos.deploy: the top, and the only package that knows every part. The ``agos`` command line,
the local launcher, ``agos demo``/``eval`` orchestration (leases, resume, progress), ``sweep``,
``check``, the configuration files and the comm profiles.
"""
