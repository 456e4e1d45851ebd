"""Navigation decisions: the route's waypoints, the flown trail, the behaviours at corners and
dead ends, the mission's state machine and its failsafe rules.

Pure bookkeeping and geometry (numpy in, numpy out, the time passed in): the flight process
(:mod:`companion.flight`) asks these what to do and does it; a notebook or a unit test can ask
the same questions without a simulator. docs/flight.md describes the behaviours.
"""
