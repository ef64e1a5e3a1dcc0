"""The fleet's evidence: the field logs of many vehicles collected into one dataset and analysed.

:mod:`.dataset` is the Parquet dataset (one folder per vehicle and day, each record once however
often it is ingested), :mod:`.ingest` collects field-log segments into it, :mod:`.analysis`
estimates per sensor what the fleet learned (turn-on bias spread, the temperature slope the set
leaves over with its standard error, drift with operating hours, a verdict), :mod:`.engine` runs
that work in process or on a Dask distributed cluster with the same result, and :mod:`.report`
writes ``sensors.csv``, ``report.md`` and plots; :mod:`.replay` replays recorded drives (CSV,
Parquet, or CAN logs read as :mod:`.drive_log` says) through two generations of sets, each
standstill's own noise estimated as :mod:`.stop_noise` says. Imports the rings below (the field
log, sets, sessions, tracking, frames, the file helpers, the ground); pyarrow, and distributed
only for a cluster.
"""

# The package's public face (tests/test_rings.py keeps it equal to what other rings import).
__all__ = ["analysis", "dataset", "drive_log", "engine", "ingest", "proposal", "proposal_files", "replay",
           "replay_plan", "report", "stop_noise"]
