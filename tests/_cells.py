"""Settings shared by the test modules that start a simulated cell."""

STATIC_ROBOT = {"truth_rate": 0.0}
"""The robot twin without its dense truth (the true tool sampled at 1 kHz of simulated time, with its
structural ring-down, into each move's trajectory record). A module whose procedures measure at rest
never reads it: once a move is done the world holds the settled pose, which is what the cameras show
and what the truth log records. Sampling it is most of the robot twin's CPU while it moves and for up
to 3 simulated seconds after each move; the modules that measure in motion keep it."""
