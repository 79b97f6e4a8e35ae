"""agos.deploy: the top, and the only package that knows every part. Its folders, top to bottom
(an import-linter layers contract in pyproject.toml keeps them in this order):

    cli/        the ``agos`` command line: one parser module per command group and the table that
                dispatches each command to the ``main`` it calls
    dataset/    AGOS-Dataset: ``agos dataset build`` (a run of the expert) and ``agos dataset stats``
    run/        run control: ``agos eval``/``demo``, the orchestrator, the local launcher and the
                settings its children get, presence and loss watches, ``--workers auto``, the
                human console, ``agos sweep``, ``agos check agent``, the episode-config builder
    recording/  the recorder process (``agos record``), one episode as a rerun file, ``agos view``
    reports/    figures from a run's records (``agos plot``) and the episode map they draw on
    ops/        operating a bus: certificates (``agos certs``), ``agos health``

Data beside them: ``configs/`` (the embedded settings), ``comm/`` (comm profiles), the compose and
router files.
"""
