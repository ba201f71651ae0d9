"""Ported controller firmware: the 1 kHz interrupt handler of [Taghirad97], stage by stage,
and the LQG joint-torque control of [Vertechy]."""
