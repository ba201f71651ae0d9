"""CiA 402 drive state machine: every transition 0-16, controlword decoding, statusword bits."""

from __future__ import annotations

import pytest
from canopen.profiles.p402 import OperationMode, State402
from hypothesis import given, settings
from hypothesis import strategies as st

from hdhil.canopen.cia402 import (
    CONTROLWORD,
    CST,
    SUPPORTED_DRIVE_MODES_BITS,
    SW_DRIVE_FOLLOWS_COMMAND,
    SW_INTERNAL_LIMIT,
    SW_QUICK_STOP,
    SW_REMOTE,
    SW_TARGET_REACHED,
    SW_VOLTAGE_ENABLED,
    SW_WARNING,
    Command,
    DriveStateMachine,
    ModeOfOperation,
    State,
    decode_controlword,
    state_from_statusword,
)

SHUTDOWN, SWITCH_ON, ENABLE, DISABLE_VOLTAGE, QUICK_STOP, FAULT_RESET = (
    0x06,
    0x07,
    0x0F,
    0x00,
    0x02,
    0x80,
)

#: Controlwords leading from SWITCH ON DISABLED to each state.
PATH = {
    State.SWITCH_ON_DISABLED: [],
    State.READY_TO_SWITCH_ON: [SHUTDOWN],
    State.SWITCHED_ON: [SHUTDOWN, SWITCH_ON],
    State.OPERATION_ENABLED: [SHUTDOWN, SWITCH_ON, ENABLE],
    State.QUICK_STOP_ACTIVE: [SHUTDOWN, SWITCH_ON, ENABLE, QUICK_STOP],
}


def drive_in(state: State, **kwargs) -> DriveStateMachine:
    drive = DriveStateMachine(**kwargs)
    drive.complete_initialisation()
    if state is State.FAULT:
        drive.fault(0x2310)
    else:
        for cw in PATH[state]:
            drive.apply_controlword(cw)
    assert drive.state is state
    return drive


def test_power_on_is_transition_0_and_init_is_1():
    drive = DriveStateMachine()
    assert drive.state is State.NOT_READY_TO_SWITCH_ON
    assert [t.number for t in drive.history] == [0]
    assert drive.history[0].old is None
    # Commands are ignored until the self-initialisation is done.
    assert drive.apply_controlword(SHUTDOWN) == ()
    assert drive.complete_initialisation() == (1,)
    assert drive.state is State.SWITCH_ON_DISABLED
    assert drive.complete_initialisation() == ()


@pytest.mark.parametrize(
    ("start", "controlword", "transitions", "end", "options"),
    [
        (State.SWITCH_ON_DISABLED, SHUTDOWN, (2,), State.READY_TO_SWITCH_ON, {}),
        (State.READY_TO_SWITCH_ON, SWITCH_ON, (3,), State.SWITCHED_ON, {}),
        (State.READY_TO_SWITCH_ON, ENABLE, (3, 4), State.OPERATION_ENABLED, {}),
        (State.SWITCHED_ON, ENABLE, (4,), State.OPERATION_ENABLED, {}),
        (State.OPERATION_ENABLED, SWITCH_ON, (5,), State.SWITCHED_ON, {}),
        (State.SWITCHED_ON, SHUTDOWN, (6,), State.READY_TO_SWITCH_ON, {}),
        (State.READY_TO_SWITCH_ON, DISABLE_VOLTAGE, (7,), State.SWITCH_ON_DISABLED, {}),
        (State.READY_TO_SWITCH_ON, QUICK_STOP, (7,), State.SWITCH_ON_DISABLED, {}),
        (State.OPERATION_ENABLED, SHUTDOWN, (8,), State.READY_TO_SWITCH_ON, {}),
        (State.OPERATION_ENABLED, DISABLE_VOLTAGE, (9,), State.SWITCH_ON_DISABLED, {}),
        (State.SWITCHED_ON, DISABLE_VOLTAGE, (10,), State.SWITCH_ON_DISABLED, {}),
        (State.SWITCHED_ON, QUICK_STOP, (10,), State.SWITCH_ON_DISABLED, {}),
        (
            State.OPERATION_ENABLED,
            QUICK_STOP,
            (11,),
            State.QUICK_STOP_ACTIVE,
            {"quick_stop_option": 6},
        ),
        (
            State.OPERATION_ENABLED,
            QUICK_STOP,
            (11, 12),
            State.SWITCH_ON_DISABLED,
            {"quick_stop_option": 2},
        ),
        (
            State.QUICK_STOP_ACTIVE,
            DISABLE_VOLTAGE,
            (12,),
            State.SWITCH_ON_DISABLED,
            {"quick_stop_option": 6},
        ),
        (
            State.QUICK_STOP_ACTIVE,
            ENABLE,
            (16,),
            State.OPERATION_ENABLED,
            {"quick_stop_option": 5},
        ),
        (State.FAULT, FAULT_RESET, (15,), State.SWITCH_ON_DISABLED, {}),
    ],
)
def test_commanded_transitions(start, controlword, transitions, end, options):
    drive = drive_in(start, **options)
    seen = []
    drive.on_transition(seen.append)
    assert drive.apply_controlword(controlword) == transitions
    assert drive.state is end
    assert [t.number for t in seen] == list(transitions)
    assert seen[-1].new is end


@pytest.mark.parametrize(
    ("start", "controlword"),
    [
        (State.SWITCH_ON_DISABLED, SWITCH_ON),  # no 2 -> 3 shortcut
        (State.SWITCH_ON_DISABLED, ENABLE),
        (State.SWITCH_ON_DISABLED, QUICK_STOP),
        (State.READY_TO_SWITCH_ON, SHUTDOWN),
        (State.SWITCHED_ON, SWITCH_ON),
        (State.OPERATION_ENABLED, ENABLE),
        (State.FAULT, SHUTDOWN),
        (State.FAULT, ENABLE),
        (State.QUICK_STOP_ACTIVE, SHUTDOWN),
    ],
)
def test_commands_without_a_transition_change_nothing(start, controlword):
    drive = drive_in(start, quick_stop_option=6)
    assert drive.apply_controlword(controlword) == ()
    assert drive.state is start


def test_transition_16_needs_quick_stop_option_5_to_8():
    drive = drive_in(State.OPERATION_ENABLED, quick_stop_option=2, quick_stop_time_s=0.01)
    assert drive.apply_controlword(QUICK_STOP) == (11,)  # ramping, still QUICK STOP ACTIVE
    assert drive.apply_controlword(ENABLE) == ()
    assert drive.state is State.QUICK_STOP_ACTIVE
    assert drive.step(0.01) == (12,)
    assert drive.state is State.SWITCH_ON_DISABLED


@pytest.mark.parametrize(
    "start",
    [
        State.SWITCH_ON_DISABLED,
        State.READY_TO_SWITCH_ON,
        State.SWITCHED_ON,
        State.OPERATION_ENABLED,
        State.QUICK_STOP_ACTIVE,
    ],
)
def test_fault_from_any_state_is_13_then_14(start):
    drive = drive_in(start, quick_stop_option=6)
    assert drive.fault(0x7300) == (13, 14)
    assert drive.state is State.FAULT
    assert drive.error_code == 0x7300
    assert not drive.torque_enabled


def test_fault_from_not_ready_and_during_fault():
    drive = DriveStateMachine()
    assert drive.fault(0x5000) == (13, 14)
    # A second fault while in FAULT changes no state but records the code.
    assert drive.fault(0x2310) == ()
    assert drive.error_code == 0x2310


def test_fault_reaction_ramp_then_14():
    drive = drive_in(State.OPERATION_ENABLED, fault_reaction_time_s=0.004)
    assert drive.torque_output(8.0) == 8.0
    assert drive.fault(0x2310) == (13,)
    assert drive.state is State.FAULT_REACTION_ACTIVE
    assert drive.statusword & 0x4F == 0x0F
    assert drive.step(0.001) == ()
    assert drive.torque_output(100.0) == pytest.approx(6.0)  # target ignored, 3/4 of 8
    assert drive.step(0.003) == (14,)
    assert drive.state is State.FAULT
    assert drive.torque_output(100.0) == 0.0


def test_fault_reset_needs_a_rising_edge_of_bit_7():
    drive = drive_in(State.FAULT)
    drive.apply_controlword(FAULT_RESET | SHUTDOWN)  # edge: reset
    assert drive.state is State.SWITCH_ON_DISABLED
    assert drive.error_code == 0
    drive.fault(0x7300)
    assert drive.apply_controlword(FAULT_RESET) == ()  # bit 7 still high: no edge
    assert drive.state is State.FAULT
    drive.apply_controlword(0)
    assert drive.apply_controlword(FAULT_RESET) == (15,)


def test_fault_reset_is_refused_while_the_condition_persists():
    drive = drive_in(State.SWITCH_ON_DISABLED)
    drive.fault(0x2310, persists=True)
    assert drive.apply_controlword(FAULT_RESET) == ()
    assert drive.state is State.FAULT
    assert drive.fault_resets_rejected == 1
    drive.clear_fault_condition()
    drive.apply_controlword(0)
    assert drive.apply_controlword(FAULT_RESET) == (15,)


def test_bit_7_set_masks_other_commands():
    drive = drive_in(State.SWITCH_ON_DISABLED)
    assert drive.apply_controlword(FAULT_RESET | SHUTDOWN) == ()  # not in FAULT: nothing
    assert drive.state is State.SWITCH_ON_DISABLED
    assert drive.apply_controlword(SHUTDOWN) == (2,)


def test_controlword_decoding_matches_the_cia402_table_and_canopen():
    assert decode_controlword(State402.CW_SHUTDOWN) is Command.SHUTDOWN
    assert decode_controlword(State402.CW_SWITCH_ON) is Command.SWITCH_ON
    assert decode_controlword(State402.CW_OPERATION_ENABLED) is Command.ENABLE_OPERATION
    assert decode_controlword(State402.CW_DISABLE_VOLTAGE) is Command.DISABLE_VOLTAGE
    assert decode_controlword(State402.CW_QUICK_STOP) is Command.QUICK_STOP
    assert decode_controlword(State402.CW_SWITCH_ON_DISABLED) is None  # fault reset bit
    # Don't-care bits: enable operation is x for shutdown, switch on x for disable voltage.
    assert decode_controlword(0x000E) is Command.SHUTDOWN
    assert decode_controlword(0x000D) is Command.DISABLE_VOLTAGE
    assert decode_controlword(0x000B) is Command.QUICK_STOP
    for command, word in CONTROLWORD.items():
        if command is not Command.FAULT_RESET:
            decoded = decode_controlword(word)
            aliases = {Command.DISABLE_OPERATION: Command.SWITCH_ON}
            assert decoded is aliases.get(command, command)


def test_statusword_patterns_match_canopens_p402_table():
    names = {
        State.NOT_READY_TO_SWITCH_ON: "NOT READY TO SWITCH ON",
        State.SWITCH_ON_DISABLED: "SWITCH ON DISABLED",
        State.READY_TO_SWITCH_ON: "READY TO SWITCH ON",
        State.SWITCHED_ON: "SWITCHED ON",
        State.OPERATION_ENABLED: "OPERATION ENABLED",
        State.QUICK_STOP_ACTIVE: "QUICK STOP ACTIVE",
        State.FAULT_REACTION_ACTIVE: "FAULT REACTION ACTIVE",
        State.FAULT: "FAULT",
    }
    for state, name in names.items():
        assert (state.mask, state.pattern) == State402.SW_MASK[name]


def _drive_in_every_state():
    yield DriveStateMachine()
    for state in PATH:
        yield drive_in(state, quick_stop_option=6)
    reacting = drive_in(State.OPERATION_ENABLED, fault_reaction_time_s=1.0)
    reacting.fault(0x1000)
    yield reacting
    yield drive_in(State.FAULT)


def test_statusword_of_every_state_decodes_back():
    states = set()
    for drive in _drive_in_every_state():
        word = drive.statusword
        assert state_from_statusword(word) is drive.state
        assert word & drive.state.mask == drive.state.pattern
        assert bool(word & SW_QUICK_STOP) == (drive.state is not State.QUICK_STOP_ACTIVE)
        states.add(drive.state)
    assert states == set(State)


def test_statusword_flag_bits():
    drive = drive_in(State.SWITCHED_ON)
    word = drive.statusword
    assert word & SW_VOLTAGE_ENABLED and word & SW_REMOTE
    assert not word & (SW_WARNING | SW_TARGET_REACHED | SW_INTERNAL_LIMIT)
    assert not word & SW_DRIVE_FOLLOWS_COMMAND
    drive.warning = drive.target_reached = drive.internal_limit_active = True
    drive.remote = drive.voltage_present = False
    word = drive.statusword
    assert word & SW_WARNING and word & SW_TARGET_REACHED and word & SW_INTERNAL_LIMIT
    assert not word & (SW_REMOTE | SW_VOLTAGE_ENABLED)
    assert word == 0x0023 | SW_QUICK_STOP | SW_WARNING | SW_TARGET_REACHED | SW_INTERNAL_LIMIT


def test_bit_12_drive_follows_the_command_in_cst_only_when_enabled():
    drive = drive_in(State.OPERATION_ENABLED)
    assert drive.statusword & SW_DRIVE_FOLLOWS_COMMAND
    assert drive.statusword == 0x0027 | SW_QUICK_STOP | SW_VOLTAGE_ENABLED | SW_REMOTE | (1 << 12)
    assert drive.set_mode(ModeOfOperation.NO_MODE)
    assert not drive.statusword & SW_DRIVE_FOLLOWS_COMMAND
    assert drive.torque_enabled  # enabled, but with no mode the target is ignored
    assert drive.torque_output(5.0) == 0.0


def test_modes_of_operation_only_cst_is_supported():
    drive = DriveStateMachine()
    assert drive.modes_of_operation == drive.modes_of_operation_display == CST == 10
    assert CST == OperationMode.CYCLIC_SYNCHRONOUS_TORQUE
    assert OperationMode.SUPPORTED["CYCLIC SYNCHRONOUS TORQUE"] == SUPPORTED_DRIVE_MODES_BITS
    assert not drive.set_mode(ModeOfOperation.PROFILE_POSITION)
    assert drive.modes_of_operation_display == CST
    with pytest.raises(ValueError):
        DriveStateMachine(mode=ModeOfOperation.HOMING)


def test_torque_enabled_only_in_operation_enabled():
    for drive in _drive_in_every_state():
        assert drive.torque_enabled == (drive.state is State.OPERATION_ENABLED)


def test_quick_stop_ramps_the_held_torque_and_ignores_new_targets():
    drive = drive_in(State.OPERATION_ENABLED, quick_stop_option=6, quick_stop_time_s=0.004)
    assert drive.torque_output(10.0) == 10.0
    assert drive.apply_controlword(QUICK_STOP) == (11,)
    assert not drive.torque_enabled
    outputs = []
    for _ in range(5):
        outputs.append(drive.torque_output(-50.0))
        drive.step(0.001)
    assert outputs == pytest.approx([10.0, 7.5, 5.0, 2.5, 0.0])
    assert drive.state is State.QUICK_STOP_ACTIVE  # option 6 stays
    assert drive.statusword & SW_TARGET_REACHED  # ramp finished
    assert drive.apply_controlword(ENABLE) == (16,)
    assert drive.torque_output(-50.0) == -50.0


def test_quick_stop_option_0_switches_torque_off_at_once():
    drive = drive_in(State.OPERATION_ENABLED, quick_stop_option=0, quick_stop_time_s=1.0)
    drive.torque_output(3.0)
    assert drive.apply_controlword(QUICK_STOP) == (11, 12)
    assert drive.torque_output(3.0) == 0.0


def test_halt_bit_is_exposed():
    drive = drive_in(State.OPERATION_ENABLED)
    drive.apply_controlword(ENABLE | 0x100)
    assert drive.halt and drive.state is State.OPERATION_ENABLED


def test_invalid_options_are_refused():
    with pytest.raises(ValueError):
        DriveStateMachine(quick_stop_option=9)
    with pytest.raises(ValueError):
        DriveStateMachine(quick_stop_time_s=-1)


@pytest.mark.slow
@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.sampled_from([SHUTDOWN, SWITCH_ON, ENABLE, DISABLE_VOLTAGE, QUICK_STOP, 0x80]),
            st.integers(0, 0xFFFF),
            st.just(-1),  # a fault
        ),
        max_size=40,
    ),
    st.sampled_from([0, 2, 6]),
)
def test_random_controlword_sequences_keep_the_invariants(words, option):
    drive = DriveStateMachine(quick_stop_option=option)
    drive.complete_initialisation()
    for word in words:
        before = drive.state
        taken = drive.fault(0x1000) if word < 0 else drive.apply_controlword(word)
        word_now = drive.statusword
        assert state_from_statusword(word_now) is drive.state
        assert drive.torque_enabled == (drive.state is State.OPERATION_ENABLED)
        if taken:
            assert drive.history[-1].new is drive.state
            assert drive.history[-len(taken)].old is before
        else:
            assert drive.state is before


#: Controlwords (0x8F: fault reset with the enable bits) and other inputs of the machine.
CONTROLWORDS_AND_EVENTS = (
    *(SHUTDOWN, SWITCH_ON, ENABLE, DISABLE_VOLTAGE, QUICK_STOP, 0x80, 0x8F),
    *("fault", "persisting fault", "clear", "step", "option 2", "option 6"),
)


def test_a_repeated_enable_in_quick_stop_follows_a_new_quick_stop_option():
    drive = drive_in(State.OPERATION_ENABLED, quick_stop_option=2, quick_stop_time_s=0.01)
    assert drive.apply_controlword(QUICK_STOP) == (11,)
    assert drive.apply_controlword(ENABLE) == ()
    assert drive.apply_controlword(ENABLE) == ()
    drive.quick_stop_option = 6
    assert drive.apply_controlword(ENABLE) == (16,)
    assert drive.state is State.OPERATION_ENABLED


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.sampled_from(CONTROLWORDS_AND_EVENTS),
            st.integers(0, 0xFFFF),
        ),
        max_size=60,
    ),
    st.sampled_from([0, 2, 6]),
)
def test_repeated_controlwords_take_the_same_transitions_as_without_the_shortcut(events, option):
    """apply_controlword skips a word that took no transition in the same state before;
    a machine that never takes the shortcut must do exactly the same (fault-reset edge,
    quick stop option changes, ramps)."""
    kwargs = dict(quick_stop_option=option, quick_stop_time_s=0.002, fault_reaction_time_s=0.002)
    fast, plain = DriveStateMachine(**kwargs), DriveStateMachine(**kwargs)
    for drive in (fast, plain):
        drive.complete_initialisation()
    for event in events:
        results = []
        for drive in (fast, plain):
            if drive is plain:
                drive._idle_state = None  # forget what was idle: the full decoding every time
            if isinstance(event, int):
                results.append(drive.apply_controlword(event))
            elif event == "fault":
                results.append(drive.fault(0x1000))
            elif event == "persisting fault":
                results.append(drive.fault(0x8130, persists=True))
            elif event == "clear":
                drive.clear_fault_condition()
                results.append(())
            elif event == "step":
                results.append(drive.step(0.001))
            else:
                drive.quick_stop_option = int(event.split()[1])
                results.append(())
        assert results[0] == results[1]
        assert fast.state is plain.state
        assert fast.statusword == plain.statusword
        assert (fast.controlword, fast.error_code, fast.fault_resets_rejected) == (
            plain.controlword,
            plain.error_code,
            plain.fault_resets_rejected,
        )
