"""The test rig: the lockstep runner that wires firmware and emulator nodes together,
the node loop and pacer, real-time OS tuning, scoring against ground truth, offline
replay of the firmware's filter and evaluation."""
