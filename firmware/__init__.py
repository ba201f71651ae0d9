"""Ported controller firmware: the 1 kHz interrupt handler of the first seed, stage by stage."""
