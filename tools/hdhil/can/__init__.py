"""The CAN floor both sides stand on: the simulated bus and its bit timing (classical
and FD), bus load and schedule planning, frame dispatch for nodes, trace writing and
reading, and fault injection. Built on python-can; imports nothing of the firmware, the
emulator or the rig."""
