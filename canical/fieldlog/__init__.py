"""What every vehicle learns at its standstills, kept as a field log a fleet can collect.

One typed record per standstill decision (adopted or refused, with the reason) and per
power-on (:mod:`.record`), written by the daemon or by ``apply --track-bias`` into small
segments of JSON lines, each closed atomically with a CRC and rotated within a size bound
(:mod:`.segments`), and read back by every consumer with damaged segments skipped in one line.
The records are made from the tracker's events (:mod:`.from_tracker`). Plain Python: the
daemon writes them without heavy dependencies; only the ground, the file helpers and the
tracking package are imported.
"""

# The package's public face (tests/test_rings.py keeps it equal to what other rings import).
__all__ = ["from_tracker", "record", "segments"]
