"""CANopen protocols on the canopen package: object-dictionary helpers, NMT, heartbeat,
EMCY, SDO, SYNC, PDO, and the CiA 402 words, states and transitions. Imports nothing
of the firmware, the emulator or the rig."""
