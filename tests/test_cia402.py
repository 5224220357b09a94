"""Exhaustive checks of the pure CiA 402 tables (drivers/cia402.py)."""
import pytest

from labbench.drivers import cia402
from labbench.drivers.cia402 import CONTROLWORD, Command, NoRoute, State


def test_every_statusword_codes_at_most_one_state():
    counts = {s: 0 for s in State}
    unknown = 0
    for sw in range(0x10000):
        matches = [s for s, (m, v) in cia402.STATUS_CODING.items() if sw & m == v]
        assert len(matches) <= 1, hex(sw)
        if matches:
            assert cia402.decode_status(sw) is matches[0]
            counts[matches[0]] += 1
        else:
            unknown += 1
            with pytest.raises(cia402.UnknownStatusword):
                cia402.decode_status(sw)
    # Mask 0x4F fixes 5 of 16 bits (2048 codes each), mask 0x6F fixes 6 (1024).
    assert counts[State.SWITCH_ON_DISABLED] == 1 << 11
    assert counts[State.OPERATION_ENABLED] == 1 << 10
    assert unknown > 0


def test_encode_decode_roundtrip_keeps_extra_bits():
    for state in State:
        sw = cia402.encode_status(state, extra_bits=cia402.SW_WARNING | cia402.SW_REMOTE | 0x6F)
        assert cia402.decode_status(sw) is state
        assert sw & cia402.SW_WARNING and sw & cia402.SW_REMOTE


# Standard examples: (state, statusword) pairs as CiA 402 drives report them.
@pytest.mark.parametrize("sw,state", [
    (0x0250, State.SWITCH_ON_DISABLED), (0x0231, State.READY_TO_SWITCH_ON),
    (0x0233, State.SWITCHED_ON), (0x0237, State.OPERATION_ENABLED),
    (0x0217, State.QUICK_STOP_ACTIVE), (0x021F, State.FAULT_REACTION_ACTIVE),
    (0x0218, State.FAULT), (0x0208, State.FAULT), (0x0000, State.NOT_READY_TO_SWITCH_ON),
])
def test_known_statuswords(sw, state):
    assert cia402.decode_status(sw) is state


def test_controlword_table_decodes_back():
    for cmd, cw in CONTROLWORD.items():
        got = cia402.decode_controlword(cw)
        # SWITCH ON and DISABLE OPERATION share 0x07.
        expected = Command.SWITCH_ON if cmd is Command.DISABLE_OPERATION else cmd
        assert got is expected, cmd


def test_fault_reset_is_an_edge_only():
    assert cia402.decode_controlword(0x80, previous=0x00) is Command.FAULT_RESET
    assert cia402.decode_controlword(0x80, previous=0x80) is Command.DISABLE_VOLTAGE
    assert cia402.decode_controlword(0x8F, previous=0x0F) is Command.FAULT_RESET


def test_all_controlwords_decode_without_error():
    for prev in (0x00, 0x80):
        for cw in range(0x100):
            cmd = cia402.decode_controlword(cw, prev)
            assert cmd is None or isinstance(cmd, Command)
            for state in State:
                assert isinstance(cia402.next_state(state, cmd), State)


def test_fault_states_ignore_everything_but_fault_reset():
    for cw in range(0x100):
        cmd = cia402.decode_controlword(cw, previous=0x80)  # no edge
        assert cia402.next_state(State.FAULT, cmd) is State.FAULT
        assert cia402.next_state(State.FAULT_REACTION_ACTIVE, cmd) is State.FAULT_REACTION_ACTIVE
    # The reset edge goes to SWITCH ON DISABLED, never further.
    assert cia402.next_state(State.FAULT, Command.FAULT_RESET) is State.SWITCH_ON_DISABLED


HOST_STATES = [State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON, State.SWITCHED_ON,
               State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE]
TARGETS = [State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON, State.SWITCHED_ON,
           State.OPERATION_ENABLED]


@pytest.mark.parametrize("start", HOST_STATES)
@pytest.mark.parametrize("target", TARGETS)
def test_paths_reach_target_through_the_drive_table(start, target):
    state = start
    for cmd, expected in cia402.path(start, target):
        state = cia402.next_state(state, cia402.decode_controlword(CONTROLWORD[cmd], 0))
        assert state is expected
        assert state not in (State.FAULT, State.FAULT_REACTION_ACTIVE)
    assert state is target
    assert len(cia402.path(start, target)) <= 4


@pytest.mark.parametrize("start", [State.FAULT, State.FAULT_REACTION_ACTIVE,
                                   State.NOT_READY_TO_SWITCH_ON])
def test_no_host_route_out_of_fault(start):
    with pytest.raises(NoRoute):
        cia402.command_toward(start, State.OPERATION_ENABLED)
    with pytest.raises(NoRoute):
        cia402.command_toward(State.SWITCH_ON_DISABLED, State.FAULT)


def test_transition_numbers_are_the_standard_ones():
    numbers = {n for _, n in cia402.TRANSITIONS.values()}
    assert numbers >= {2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 15, 16}
    # Every transition leaving OPERATION ENABLED removes torque or keeps it via quick stop.
    for (state, _), (nxt, _) in cia402.TRANSITIONS.items():
        if state is State.OPERATION_ENABLED:
            assert nxt in (State.SWITCHED_ON, State.READY_TO_SWITCH_ON,
                           State.SWITCH_ON_DISABLED, State.QUICK_STOP_ACTIVE)
