"""The controller's CiA 402 walk of the drive's power drive system (CiA 402-2 state
machine), as decisions: for the drive's latest statusword, which controlword to send or
which link phase to enter.

==========================  ==================  ==========================================
drive state (statusword)    controlword sent    note
==========================  ==================  ==========================================
unknown, NOT READY, SWITCH  0x0006 shutdown     transition 2
ON DISABLED
READY TO SWITCH ON          0x0007 switch on    transition 3
SWITCHED ON                 0x000F enable op.   transition 4
OPERATION ENABLED           0x000F              "operational"
QUICK STOP ACTIVE           0x0000              disable voltage (transition 12), walk again
FAULT REACTION ACTIVE       unchanged           wait for FAULT
FAULT                       0x0080 fault reset  rising edge of bit 7 (transition 15), then
                                                walk again; **one** fault reset per node:
                                                a second fault, or a refused reset, -> safe
==========================  ==================  ==========================================

The walk back (stop): 0x0007 "disable operation" (5), then 0x0006 "shutdown" (6).  The
node (:mod:`hdhil.firmware.controller`) sends the controlword and handles the phases and
timeouts; this class only decides.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal, NamedTuple

from hdhil.canopen.cia402 import CONTROLWORD, CW_FAULT_RESET, Command, State, state_from_statusword

__all__ = ["CONTROLWORD_ENABLE_OPERATION", "Cia402Walk", "WalkStep"]

#: CiA 402 controlword "enable operation" (switch on, enable voltage, quick stop off,
#: enable operation).  The drive amplifier follows the DAC command only while enabled.
CONTROLWORD_ENABLE_OPERATION = CONTROLWORD[Command.ENABLE_OPERATION]
SHUTDOWN = CONTROLWORD[Command.SHUTDOWN]  # 0x0006
SWITCH_ON = CONTROLWORD[Command.SWITCH_ON]  # 0x0007, also "disable operation"
DISABLE_VOLTAGE = CONTROLWORD[Command.DISABLE_VOLTAGE]  # 0x0000
FAULT_RESET = CONTROLWORD[Command.FAULT_RESET]  # 0x0080


class WalkStep(NamedTuple):
    """What the node does next: keep walking ("walk", the controlword is set), enter
    "operational", restart the walk after a drive fault ("restart"), end the stop
    ("stopped") or give up ("safe"); ``reason`` is the phase history's text."""

    action: Literal["walk", "operational", "restart", "stopped", "safe"]
    reason: str = ""


_WALK = WalkStep("walk")


class Cia402Walk:
    """Controlword, last statusword and fault resets of one commanded drive.

    ``on_controlword(cw)`` runs when the controlword changes (the node mirrors it into
    its 0x6040).  ``cw_sends`` counts the commands sent with the present controlword
    (the node increments it), so a fault reset that the drive refused is told apart
    from one not yet sent.
    """

    #: Automatic fault resets per node lifetime (CiA 402 transition 15).
    MAX_FAULT_RESETS = 1

    def __init__(self, drive_node_id: int, on_controlword: Callable[[int], None]) -> None:
        self.drive_node_id = drive_node_id
        self.on_controlword = on_controlword
        self.controlword = SHUTDOWN
        self.cw_sends = 0
        self.drive_state: State | None = None
        self.statusword: int | None = None
        self.fault_resets = 0

    def set_controlword(self, controlword: int) -> None:
        if controlword != self.controlword:
            self.controlword = controlword
            self.cw_sends = 0
            self.on_controlword(controlword)

    def on_statusword(self, statusword: int) -> bool:
        """Record a statusword; False if it codes no CiA 402 state."""
        self.statusword = statusword
        try:
            self.drive_state = state_from_statusword(statusword)
        except ValueError:
            return False
        return True

    def restart(self) -> None:
        """A new walk up (NMT start of the drive): state unknown, "shutdown" first."""
        self.drive_state = None
        self.set_controlword(SHUTDOWN)

    def state_text(self) -> str:
        state = self.drive_state
        name = state.name.replace("_", " ") if state is not None else "unknown"
        sw = self.statusword
        return f"{name}, statusword 0x{sw:04X}" if sw is not None else name

    def fault_text(self, what: str) -> str:
        return f"{what} ({self.state_text()})"

    # ---------------------------------------------------------------- decisions

    def in_operation(self) -> WalkStep:
        """The drive's state while "operational"."""
        state = self.drive_state
        if state is State.OPERATION_ENABLED:
            return _WALK
        if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            if self.fault_resets < self.MAX_FAULT_RESETS:
                return WalkStep("restart", self.fault_text("drive fault") + ": reset")
            return WalkStep("safe", self.fault_text("drive fault again after a fault reset"))
        return WalkStep(
            "safe",
            f"drive (node {self.drive_node_id}) left OPERATION ENABLED on its own: "
            f"{self.state_text()}",
        )

    def up(self) -> WalkStep:
        """The next step of the start-up walk."""
        state = self.drive_state
        if state is None or state in (State.NOT_READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED):
            self.set_controlword(SHUTDOWN)  # transition 2
        elif state is State.READY_TO_SWITCH_ON:
            self.set_controlword(SWITCH_ON)  # transition 3
        elif state is State.SWITCHED_ON:
            self.set_controlword(CONTROLWORD_ENABLE_OPERATION)  # transition 4
        elif state is State.OPERATION_ENABLED:
            self.set_controlword(CONTROLWORD_ENABLE_OPERATION)
            return WalkStep("operational", "drive reports OPERATION ENABLED")
        elif state is State.QUICK_STOP_ACTIVE:
            self.set_controlword(DISABLE_VOLTAGE)  # transition 12
        elif state is State.FAULT:
            if self.controlword & CW_FAULT_RESET:
                if self.cw_sends:  # reset sent, drive still in FAULT: refused
                    return WalkStep("safe", self.fault_text("drive refused the fault reset"))
            elif self.fault_resets < self.MAX_FAULT_RESETS:
                self.fault_resets += 1
                self.set_controlword(FAULT_RESET)  # rising edge of bit 7 (transition 15)
            else:
                return WalkStep("safe", self.fault_text("drive fault again after a fault reset"))
        # FAULT REACTION ACTIVE: wait for FAULT with the controlword unchanged.
        return _WALK

    def down(self) -> WalkStep:
        """The next step of the stop walk."""
        state = self.drive_state
        if state is State.OPERATION_ENABLED:
            self.set_controlword(SWITCH_ON)  # disable operation (transition 5)
        elif state is State.SWITCHED_ON or state is None:
            self.set_controlword(SHUTDOWN)  # transition 6
        elif state is not State.FAULT_REACTION_ACTIVE:
            return WalkStep("stopped", f"drive stopped: {self.state_text()}")
        return _WALK
