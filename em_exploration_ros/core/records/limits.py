"""Bounds of any number or id a process accepts from another: beyond them a value is corrupt."""

#: Largest magnitude of any number in a message (coordinates [m], variances [m^2],
#: velocities, times [s]); beyond it a value is treated as corrupt (1e9 m is 25 times
#: the Earth's circumference).
MAX_ABS_VALUE = 1e9
#: Largest id of anything (landmark, decision, rendezvous): ids are small counters.
MAX_ID = 2**31 - 1
