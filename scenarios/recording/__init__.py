"""rerun recordings of runs and captures, live and after the fact (the only place that imports
rerun): `log` holds the ``log_*`` functions, `observer` the live session, `replay` the replay."""
