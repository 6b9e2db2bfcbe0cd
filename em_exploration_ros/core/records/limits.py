"""Bounds of any number or id a process accepts from another: beyond them a value is corrupt."""

#: Largest magnitude of any number in a message (coordinates [m], variances [m^2],
#: velocities, times [s]); beyond it a value is treated as corrupt (1e9 m is 25 times
#: the Earth's circumference).
MAX_ABS_VALUE = 1e9
#: Largest id of anything (landmark, decision, rendezvous): ids are small counters.
MAX_ID = 2**31 - 1
#: Largest serialized team update [B] a receiver still reads when it already holds the record
#: (its sequence number is below the next one expected: ignored whatever it holds, read only
#: to say what is wrong with it). A larger one is ignored unread: a record of a few readings
#: is a few hundred bytes and deserializes in under a millisecond; em-fuzz's of 100-300 kB
#: (thousands of nested messages) took rclpy 30-180 ms each, and a flood of them held the
#: robots tens of seconds behind the lockstep barrier.
MAX_HELD_RECORD_READ_BYTES = 16_384
#: Liveliness writers (processes) a watcher remembers per robot, to tell a restarted robot
#: from one whose liveliness came back: a run restarts a robot a few times at most; a flood
#: of identities on its alive topic makes the watcher forget those absent longest.
MAX_LIVELINESS_WRITERS = 64
#: Status changes (lost, rejoined, finished) of a robot a run's summary lists: the first and
#: the latest half; a run has a few, a flood of liveliness identities two for each.
MAX_STATUS_CHANGES = 200
