"""Time as the CANopen services see it: explicit ``now`` values, never a wall clock.

Every protocol module here is driven by the caller's clock (simulated time in lockstep,
``time.monotonic()`` in real time), so lockstep runs stay deterministic: no threads, no
timers, no ``send_periodic``.
"""

#: Time tolerance for due/deadline comparisons, so float rounding of the caller's clock
#: never moves a heartbeat or a timeout by a whole tick.
TIME_EPSILON = 1e-9
