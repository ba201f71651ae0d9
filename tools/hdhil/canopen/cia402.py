"""CiA 402 drive state machine (power drive system, PDS FSA), pure and bus-agnostic.

CiA 402-2 / IEC 61800-7-201, clause "PDS finite state automaton": the drive is in one of
eight states; the controlword (0x6040) commands transitions 0-16, the statusword (0x6041)
reports the state, and a fault takes the drive to FAULT REACTION ACTIVE and then FAULT.
Nothing here touches a bus or a clock: the drive node feeds controlwords, faults and
elapsed time in, and reads the statusword, ``torque_enabled`` and ``torque_output(...)``.

Modes of operation 0x6060/0x6061: cyclic synchronous torque (CST, 10) is the supported
mode and the default; "no mode" (0) makes the drive ignore its target; any other mode is
rejected (``set_mode`` returns False).  Quick stop (option code 0x605A) and the fault
reaction (0x605E) ramp the torque being applied linearly to zero over
``quick_stop_time_s`` / ``fault_reaction_time_s`` (our stand-in for the torque slope
0x6087); quick stop options 5-8 then stay in QUICK STOP ACTIVE until Enable operation
(transition 16).  ``torque_enabled`` is True only in OPERATION ENABLED, the only state in
which the drive follows its torque target.

The transition table, the controlword coding and the statusword bits set here are in
docs/canopen.md, "The CiA 402 state machine".
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum, IntEnum


class State(Enum):
    """PDS states with their statusword (mask, value) pattern (CiA 402-2 table)."""

    NOT_READY_TO_SWITCH_ON = (0x4F, 0x00)
    SWITCH_ON_DISABLED = (0x4F, 0x40)
    READY_TO_SWITCH_ON = (0x6F, 0x21)
    SWITCHED_ON = (0x6F, 0x23)
    OPERATION_ENABLED = (0x6F, 0x27)
    QUICK_STOP_ACTIVE = (0x6F, 0x07)
    FAULT_REACTION_ACTIVE = (0x4F, 0x0F)
    FAULT = (0x4F, 0x08)

    def __init__(self, mask: int, pattern: int) -> None:
        # Plain attributes, not properties over ``value``: the statusword is built from
        # ``pattern`` several times per cycle.
        self.mask = mask
        self.pattern = pattern


class Command(Enum):
    """Device control commands (CiA 402-2 "command coding")."""

    SHUTDOWN = "shutdown"
    SWITCH_ON = "switch on"  # also "disable operation" (same bit pattern)
    ENABLE_OPERATION = "enable operation"  # also "switch on + enable operation"
    DISABLE_VOLTAGE = "disable voltage"
    QUICK_STOP = "quick stop"
    DISABLE_OPERATION = "disable operation"
    FAULT_RESET = "fault reset"


#: A typical controlword for each command (the don't-care bits cleared).
CONTROLWORD: dict[Command, int] = {
    Command.SHUTDOWN: 0x0006,
    Command.SWITCH_ON: 0x0007,
    Command.DISABLE_OPERATION: 0x0007,
    Command.ENABLE_OPERATION: 0x000F,
    Command.DISABLE_VOLTAGE: 0x0000,
    Command.QUICK_STOP: 0x0002,
    Command.FAULT_RESET: 0x0080,
}

#: EDS ParameterName of the CiA 402 objects the nodes use: they find the objects by name
#: in their object dictionaries (``hdhil.canopen.od.index_of``), the numbers live in the
#: EDS files only.
CONTROLWORD_OBJECT = "controlword"
STATUSWORD_OBJECT = "statusword"
#: Cyclic synchronous torque objects (CiA 402-2): torques in per mille of the motor rated
#: torque, position in increments, velocity in increments per second.
TARGET_TORQUE_OBJECT = "target_torque"  # 0x6071 INTEGER16
MAX_TORQUE_OBJECT = "max_torque"  # 0x6072 UNSIGNED16
RATED_TORQUE_OBJECT = "motor_rated_torque"  # 0x6076 UNSIGNED32, mNm
TORQUE_ACTUAL_OBJECT = "torque_actual_value"  # 0x6077 INTEGER16
POSITION_ACTUAL_OBJECT = "position_actual_value"  # 0x6064 INTEGER32
VELOCITY_ACTUAL_OBJECT = "velocity_actual_value"  # 0x606C INTEGER32

# Controlword bits (CiA 402-2, object 0x6040).
CW_SWITCH_ON = 1 << 0
CW_ENABLE_VOLTAGE = 1 << 1
CW_QUICK_STOP = 1 << 2  # active low: 0 requests a quick stop
CW_ENABLE_OPERATION = 1 << 3
CW_FAULT_RESET = 1 << 7
CW_HALT = 1 << 8

# Statusword bits (CiA 402-2, object 0x6041).
SW_READY_TO_SWITCH_ON = 1 << 0
SW_SWITCHED_ON = 1 << 1
SW_OPERATION_ENABLED = 1 << 2
SW_FAULT = 1 << 3
SW_VOLTAGE_ENABLED = 1 << 4
SW_QUICK_STOP = 1 << 5  # active low
SW_SWITCH_ON_DISABLED = 1 << 6
SW_WARNING = 1 << 7
SW_REMOTE = 1 << 9
SW_TARGET_REACHED = 1 << 10
SW_INTERNAL_LIMIT = 1 << 11
SW_DRIVE_FOLLOWS_COMMAND = 1 << 12  # cyclic synchronous modes


class ModeOfOperation(IntEnum):
    """Modes of operation, objects 0x6060/0x6061 (CiA 402-2; values as in canopen's p402)."""

    NO_MODE = 0
    PROFILE_POSITION = 1
    VELOCITY = 2
    PROFILE_VELOCITY = 3
    PROFILE_TORQUE = 4
    HOMING = 6
    INTERPOLATED_POSITION = 7
    CYCLIC_SYNCHRONOUS_POSITION = 8
    CYCLIC_SYNCHRONOUS_VELOCITY = 9
    CYCLIC_SYNCHRONOUS_TORQUE = 10


CST = ModeOfOperation.CYCLIC_SYNCHRONOUS_TORQUE
#: Modes this drive accepts in 0x6060.
SUPPORTED_MODES: frozenset[int] = frozenset({ModeOfOperation.NO_MODE, CST})
#: Object 0x6502 "supported drive modes": bit (mode - 1) per supported mode; CST is bit 9.
SUPPORTED_DRIVE_MODES_BITS = 1 << (CST - 1)

#: Transition numbers per (old, new) state for the commanded/automatic transitions.
TRANSITIONS: dict[tuple[State, State], int] = {
    (State.NOT_READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED): 1,
    (State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON): 2,
    (State.READY_TO_SWITCH_ON, State.SWITCHED_ON): 3,
    (State.SWITCHED_ON, State.OPERATION_ENABLED): 4,
    (State.OPERATION_ENABLED, State.SWITCHED_ON): 5,
    (State.SWITCHED_ON, State.READY_TO_SWITCH_ON): 6,
    (State.READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED): 7,
    (State.OPERATION_ENABLED, State.READY_TO_SWITCH_ON): 8,
    (State.OPERATION_ENABLED, State.SWITCH_ON_DISABLED): 9,
    (State.SWITCHED_ON, State.SWITCH_ON_DISABLED): 10,
    (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE): 11,
    (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED): 12,
    (State.FAULT_REACTION_ACTIVE, State.FAULT): 14,
    (State.FAULT, State.SWITCH_ON_DISABLED): 15,
    (State.QUICK_STOP_ACTIVE, State.OPERATION_ENABLED): 16,
}

# Where each command leads from each state (absent = the command has no effect there).
_NEXT: dict[State, dict[Command, State]] = {
    State.SWITCH_ON_DISABLED: {Command.SHUTDOWN: State.READY_TO_SWITCH_ON},
    State.READY_TO_SWITCH_ON: {
        Command.SWITCH_ON: State.SWITCHED_ON,
        Command.ENABLE_OPERATION: State.SWITCHED_ON,  # 3, then 4 automatically
        Command.DISABLE_VOLTAGE: State.SWITCH_ON_DISABLED,
        Command.QUICK_STOP: State.SWITCH_ON_DISABLED,
    },
    State.SWITCHED_ON: {
        Command.ENABLE_OPERATION: State.OPERATION_ENABLED,
        Command.SHUTDOWN: State.READY_TO_SWITCH_ON,
        Command.DISABLE_VOLTAGE: State.SWITCH_ON_DISABLED,
        Command.QUICK_STOP: State.SWITCH_ON_DISABLED,
    },
    State.OPERATION_ENABLED: {
        Command.SWITCH_ON: State.SWITCHED_ON,  # "disable operation"
        Command.SHUTDOWN: State.READY_TO_SWITCH_ON,
        Command.DISABLE_VOLTAGE: State.SWITCH_ON_DISABLED,
        Command.QUICK_STOP: State.QUICK_STOP_ACTIVE,
    },
    State.QUICK_STOP_ACTIVE: {Command.DISABLE_VOLTAGE: State.SWITCH_ON_DISABLED},
}

# The states the per-cycle code tests for, as module globals: an attribute of an Enum
# class (``State.FAULT``) is looked up through ``EnumType.__getattr__``'s slow path in
# Python 3.11, several times slower than a global.
_OPERATION_ENABLED = State.OPERATION_ENABLED
_QUICK_STOP_ACTIVE = State.QUICK_STOP_ACTIVE
_FAULT_REACTION_ACTIVE = State.FAULT_REACTION_ACTIVE


def decode_controlword(controlword: int) -> Command | None:
    """The command a controlword codes, ignoring the fault-reset edge (needs history).

    Returns None while bit 7 (fault reset) is set: every other command needs it clear.
    """
    if controlword & CW_FAULT_RESET:
        return None
    if not controlword & CW_ENABLE_VOLTAGE:
        return Command.DISABLE_VOLTAGE
    if not controlword & CW_QUICK_STOP:
        return Command.QUICK_STOP
    if not controlword & CW_SWITCH_ON:
        return Command.SHUTDOWN
    if not controlword & CW_ENABLE_OPERATION:
        return Command.SWITCH_ON
    return Command.ENABLE_OPERATION


def state_from_statusword(statusword: int) -> State:
    """Decode the PDS state from a statusword (the inverse of the pattern table)."""
    for state in State:
        if statusword & state.mask == state.pattern:
            return state
    raise ValueError(f"statusword 0x{statusword:04X} codes no CiA 402 state")


@dataclass(frozen=True)
class Transition:
    """One state change: CiA 402 transition number, states, and what caused it."""

    number: int
    old: State | None
    new: State
    cause: str


TransitionCallback = Callable[[Transition], None]


class DriveStateMachine:
    """The CiA 402 PDS state machine of one drive axis.

    Construction is transition 0 (state NOT READY TO SWITCH ON); call
    ``complete_initialisation()`` when the drive's self-test is done (transition 1).
    """

    def __init__(
        self,
        *,
        quick_stop_option: int = 2,
        quick_stop_time_s: float = 0.0,
        fault_reaction_time_s: float = 0.0,
        mode: int = CST,
        on_transition: TransitionCallback | None = None,
        history: int = 256,
    ) -> None:
        if not 0 <= quick_stop_option <= 8:
            raise ValueError(f"quick stop option code must be 0..8, got {quick_stop_option}")
        if quick_stop_time_s < 0 or fault_reaction_time_s < 0:
            raise ValueError("ramp times must be >= 0")
        if mode not in SUPPORTED_MODES:
            raise ValueError(f"mode {mode} not supported (supported: {sorted(SUPPORTED_MODES)})")
        #: 0x605A quick stop option code.
        self.quick_stop_option = quick_stop_option
        self.quick_stop_time_s = quick_stop_time_s
        self.fault_reaction_time_s = fault_reaction_time_s
        #: 0x6060 modes of operation (requested) and 0x6061 display (active).
        self.modes_of_operation = int(mode)
        self.modes_of_operation_display = int(mode)
        #: 0x603F error code of the last fault (0 after a successful fault reset).
        self.error_code = 0
        #: Statusword flags the application sets.
        self.warning = False
        self.remote = True
        self.target_reached = False
        self.internal_limit_active = False
        self.voltage_present = True
        #: Counters.
        self.fault_resets_rejected = 0
        self.history: deque[Transition] = deque(maxlen=history)
        self._callbacks: list[TransitionCallback] = []
        if on_transition is not None:
            self._callbacks.append(on_transition)
        self.controlword = 0
        self._fault_condition = False
        self._ramp_left_s = 0.0  # remaining quick-stop / fault-reaction ramp
        self._ramp_total_s = 0.0
        self._held_torque = 0.0
        # The last (controlword, state) that took no transition (see apply_controlword).
        self._idle_controlword: int | None = None
        self._idle_state: State | None = None
        self.state = State.NOT_READY_TO_SWITCH_ON
        self._record(Transition(0, None, self.state, "power on"))

    # ------------------------------------------------------------------ inputs

    def on_transition(self, callback: TransitionCallback) -> TransitionCallback:
        """Register ``callback(transition)``, called after every state change."""
        self._callbacks.append(callback)
        return callback

    def complete_initialisation(self) -> tuple[int, ...]:
        """Transition 1: self-initialisation done (only from NOT READY TO SWITCH ON)."""
        if self.state is not State.NOT_READY_TO_SWITCH_ON:
            return ()
        return (self._go(State.SWITCH_ON_DISABLED, "initialisation complete"),)

    def apply_controlword(self, controlword: int) -> tuple[int, ...]:
        """Process a controlword (0x6040); returns the transition numbers taken."""
        controlword &= 0xFFFF
        previous = self.controlword
        self.controlword = controlword
        if controlword & CW_FAULT_RESET:
            if previous & CW_FAULT_RESET or self.state is not State.FAULT:
                return ()
            if self._fault_condition:
                self.fault_resets_rejected += 1
                return ()
            self.error_code = 0
            return (self._go(State.SWITCH_ON_DISABLED, "fault reset"),)
        state = self.state
        if controlword == self._idle_controlword and state is self._idle_state:
            # This word took no transition in this state before, and without bit 7 the
            # outcome depends on the word and the state alone (the cyclic command
            # repeats its controlword every cycle).
            return ()
        command = decode_controlword(controlword)
        assert command is not None
        if state is State.QUICK_STOP_ACTIVE and command is Command.ENABLE_OPERATION:
            # Depends on the quick stop option code as well: never remembered as idle.
            if self.quick_stop_option >= 5:
                return (self._go(State.OPERATION_ENABLED, command.value),)
            return ()
        target = _NEXT.get(state, {}).get(command)
        if target is None:
            self._idle_controlword = controlword
            self._idle_state = state
            return ()
        if target is State.QUICK_STOP_ACTIVE:
            return self._start_quick_stop()
        taken = [self._go(target, command.value)]
        if state is State.READY_TO_SWITCH_ON and command is Command.ENABLE_OPERATION:
            taken.append(self._go(State.OPERATION_ENABLED, "switch on + enable operation"))
        return tuple(taken)

    def fault(self, code: int, *, persists: bool = False) -> tuple[int, ...]:
        """A fault occurred (transition 13, then 14 when the reaction is instantaneous).

        ``code`` goes to 0x603F (use the CiA 402 / CiA 301 EMCY codes).  With ``persists``
        the fault condition is still present and fault reset is refused until
        ``clear_fault_condition()``.
        """
        self.error_code = code & 0xFFFF
        self._fault_condition = persists
        if self.state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            return ()
        self._held_torque = self._present_demand()
        taken = [self._go(State.FAULT_REACTION_ACTIVE, f"fault 0x{code:04X}", number=13)]
        self._ramp_total_s = self._ramp_left_s = self.fault_reaction_time_s
        if self._ramp_left_s <= 0:
            taken.append(self._go(State.FAULT, "fault reaction complete"))
        return tuple(taken)

    def clear_fault_condition(self) -> None:
        """The cause of the last fault is gone: a fault reset will now succeed."""
        self._fault_condition = False

    def step(self, dt: float) -> tuple[int, ...]:
        """Advance the quick-stop / fault-reaction ramp by ``dt`` seconds."""
        state = self.state  # _ramping, inline: every cycle of an enabled drive returns here
        if not (
            (state is _QUICK_STOP_ACTIVE or state is _FAULT_REACTION_ACTIVE)
            and self._ramp_left_s > 0
        ):
            return ()
        self._ramp_left_s = max(0.0, self._ramp_left_s - dt)
        if self._ramp_left_s > 0:
            return ()
        if self.state is State.FAULT_REACTION_ACTIVE:
            return (self._go(State.FAULT, "fault reaction complete"),)
        if self.quick_stop_option <= 4:
            return (self._go(State.SWITCH_ON_DISABLED, "quick stop complete"),)
        return ()

    def set_mode(self, mode: int) -> bool:
        """Write 0x6060; True if the mode is supported (0x6061 then shows it)."""
        if mode not in SUPPORTED_MODES:
            return False
        self.modes_of_operation = self.modes_of_operation_display = int(mode)
        return True

    # ----------------------------------------------------------------- outputs

    @property
    def torque_enabled(self) -> bool:
        """True only in OPERATION ENABLED: the drive follows its torque target."""
        return self.state is State.OPERATION_ENABLED

    @property
    def follows_command(self) -> bool:
        """OPERATION ENABLED in mode CST (statusword bit 12 in cyclic synchronous modes)."""
        return self.state is _OPERATION_ENABLED and self.modes_of_operation_display == CST

    @property
    def halt(self) -> bool:
        """Controlword bit 8 (halt); the drive decides what halting means for its mode."""
        return bool(self.controlword & CW_HALT)

    @property
    def torque_factor(self) -> float:
        """1 in OPERATION ENABLED, the ramp (1 -> 0) during quick stop / fault reaction, else 0."""
        if self.state is State.OPERATION_ENABLED:
            return 1.0
        if self._ramping and self._ramp_total_s > 0:
            return self._ramp_left_s / self._ramp_total_s
        return 0.0

    def torque_output(self, target: float) -> float:
        """The torque demand to apply for this target (see the module docstring)."""
        if self.state is _OPERATION_ENABLED:
            if self.modes_of_operation_display == CST:  # follows_command
                self._held_torque = target
                return target
            self._held_torque = 0.0  # mode "no mode": ignore the target
            return 0.0
        return self._held_torque * self.torque_factor

    @property
    def statusword(self) -> int:
        """Object 0x6041 for the present state and flags."""
        state = self.state
        word = state.pattern
        if state is not _QUICK_STOP_ACTIVE:
            word |= SW_QUICK_STOP
        if self.voltage_present:
            word |= SW_VOLTAGE_ENABLED
        if self.warning:
            word |= SW_WARNING
        if self.remote:
            word |= SW_REMOTE
        if self.target_reached or (state is _QUICK_STOP_ACTIVE and not self._ramping):
            word |= SW_TARGET_REACHED
        if self.internal_limit_active:
            word |= SW_INTERNAL_LIMIT
        if state is _OPERATION_ENABLED and self.modes_of_operation_display == CST:
            word |= SW_DRIVE_FOLLOWS_COMMAND  # follows_command
        return word

    # ---------------------------------------------------------------- internals

    @property
    def _ramping(self) -> bool:
        state = self.state
        return (state is _QUICK_STOP_ACTIVE or state is _FAULT_REACTION_ACTIVE) and (
            self._ramp_left_s > 0
        )

    def _present_demand(self) -> float:
        # The held demand times the factor: the target in OPERATION ENABLED, the ramped
        # value during a ramp, 0 elsewhere (the held value is cleared on leaving).
        return self._held_torque * self.torque_factor

    def _start_quick_stop(self) -> tuple[int, ...]:
        self._held_torque = self._present_demand()
        taken = [self._go(State.QUICK_STOP_ACTIVE, Command.QUICK_STOP.value)]
        option = self.quick_stop_option
        self._ramp_total_s = self._ramp_left_s = 0.0 if option == 0 else self.quick_stop_time_s
        if self._ramp_left_s <= 0 and option <= 4:
            taken.append(self._go(State.SWITCH_ON_DISABLED, "quick stop complete"))
        return tuple(taken)

    def _go(self, new: State, cause: str, number: int | None = None) -> int:
        old = self.state
        if number is None:
            number = TRANSITIONS[(old, new)]
        self.state = new
        if new not in (State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE):
            self._ramp_left_s = 0.0
        if new is not State.OPERATION_ENABLED and new not in (
            State.QUICK_STOP_ACTIVE,
            State.FAULT_REACTION_ACTIVE,
        ):
            self._held_torque = 0.0
        self._record(Transition(number, old, new, cause))
        return number

    def _record(self, transition: Transition) -> None:
        self.history.append(transition)
        for callback in self._callbacks:
            callback(transition)
