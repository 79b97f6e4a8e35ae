"""Run control: ``agos eval`` and ``agos demo`` (evaluate, demo), the orchestrator that leases
episodes, the launcher that starts the local processes and the environment each child gets its
settings from (children), the watches that stop a run going nowhere (presence), how many episodes
run at once (concurrency), the human console of a run (human), ``agos sweep`` (sweep), ``agos
check agent`` (check) and the one builder of a run's episode configuration (configure)."""
