"""CiA 402 drive state machine as pure tables: no I/O, no clocks.

Both sides use it: the host driver (``labbench.drivers.canopen_drive``) to decode the
statusword and pick the next controlword on the way to a target state, and the
simulated drive (``labbench.sim_backend.canopen_peer``) to react to a controlword.
Source: CiA 402-2 (IEC 61800-7-201), "drive state machine", the statusword
masks and the controlword command table; transition numbers are the standard's.

Unlike canopen's ``BaseNode402`` the host never passes through FAULT on its own:
``path()`` refuses a route out of FAULT, and ``FAULT_RESET`` leads to SWITCH ON
DISABLED only (transition 15), on the operator's request.
"""
from __future__ import annotations

import enum


class State(enum.Enum):
    NOT_READY_TO_SWITCH_ON = "NOT READY TO SWITCH ON"
    SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
    READY_TO_SWITCH_ON = "READY TO SWITCH ON"
    SWITCHED_ON = "SWITCHED ON"
    OPERATION_ENABLED = "OPERATION ENABLED"
    QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
    FAULT_REACTION_ACTIVE = "FAULT REACTION ACTIVE"
    FAULT = "FAULT"


class Command(enum.Enum):
    SHUTDOWN = "shutdown"
    SWITCH_ON = "switch on"
    DISABLE_VOLTAGE = "disable voltage"
    QUICK_STOP = "quick stop"
    DISABLE_OPERATION = "disable operation"
    ENABLE_OPERATION = "enable operation"
    FAULT_RESET = "fault reset"


# Statusword: (mask, value) over bits 0-3, 5, 6 (CiA 402-2 table "state coding").
STATUS_CODING = {
    State.NOT_READY_TO_SWITCH_ON: (0x4F, 0x00),
    State.SWITCH_ON_DISABLED: (0x4F, 0x40),
    State.READY_TO_SWITCH_ON: (0x6F, 0x21),
    State.SWITCHED_ON: (0x6F, 0x23),
    State.OPERATION_ENABLED: (0x6F, 0x27),
    State.QUICK_STOP_ACTIVE: (0x6F, 0x07),
    State.FAULT_REACTION_ACTIVE: (0x4F, 0x0F),
    State.FAULT: (0x4F, 0x08),
}

# Other statusword bits the host watches.
SW_VOLTAGE_ENABLED = 1 << 4
SW_WARNING = 1 << 7
SW_REMOTE = 1 << 9
SW_TARGET_REACHED = 1 << 10
SW_INTERNAL_LIMIT = 1 << 11

# Controlword the host sends for each command (bits 0-3 and 7). FAULT_RESET is
# the rising edge of bit 7: the host sends 0x00 first, then 0x80.
CONTROLWORD = {
    Command.SHUTDOWN: 0x06,
    Command.SWITCH_ON: 0x07,
    Command.DISABLE_VOLTAGE: 0x00,
    Command.QUICK_STOP: 0x02,
    Command.DISABLE_OPERATION: 0x07,
    Command.ENABLE_OPERATION: 0x0F,
    Command.FAULT_RESET: 0x80,
}

S = State
C = Command
# Drive-side transitions: (state, command) -> (next state, CiA 402 transition number).
# States absent for a command ignore it. Transitions 0, 1, 13, 14 are internal
# (power-up, fault detection) and live in the drive, not in this table.
TRANSITIONS = {
    (S.SWITCH_ON_DISABLED, C.SHUTDOWN): (S.READY_TO_SWITCH_ON, 2),
    (S.READY_TO_SWITCH_ON, C.SWITCH_ON): (S.SWITCHED_ON, 3),
    (S.READY_TO_SWITCH_ON, C.ENABLE_OPERATION): (S.OPERATION_ENABLED, 34),  # 3 then 4
    (S.SWITCHED_ON, C.ENABLE_OPERATION): (S.OPERATION_ENABLED, 4),
    (S.OPERATION_ENABLED, C.DISABLE_OPERATION): (S.SWITCHED_ON, 5),
    (S.SWITCHED_ON, C.SHUTDOWN): (S.READY_TO_SWITCH_ON, 6),
    (S.READY_TO_SWITCH_ON, C.DISABLE_VOLTAGE): (S.SWITCH_ON_DISABLED, 7),
    (S.READY_TO_SWITCH_ON, C.QUICK_STOP): (S.SWITCH_ON_DISABLED, 7),
    (S.OPERATION_ENABLED, C.SHUTDOWN): (S.READY_TO_SWITCH_ON, 8),
    (S.OPERATION_ENABLED, C.DISABLE_VOLTAGE): (S.SWITCH_ON_DISABLED, 9),
    (S.SWITCHED_ON, C.DISABLE_VOLTAGE): (S.SWITCH_ON_DISABLED, 10),
    (S.SWITCHED_ON, C.QUICK_STOP): (S.SWITCH_ON_DISABLED, 10),
    (S.OPERATION_ENABLED, C.QUICK_STOP): (S.QUICK_STOP_ACTIVE, 11),
    (S.QUICK_STOP_ACTIVE, C.DISABLE_VOLTAGE): (S.SWITCH_ON_DISABLED, 12),
    (S.FAULT, C.FAULT_RESET): (S.SWITCH_ON_DISABLED, 15),
    (S.QUICK_STOP_ACTIVE, C.ENABLE_OPERATION): (S.OPERATION_ENABLED, 16),
}

# States in which the power stage may produce torque.
TORQUE_STATES = frozenset({S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE, S.FAULT_REACTION_ACTIVE})


class UnknownStatusword(ValueError):
    """A statusword that matches no CiA 402 state."""


def decode_status(statusword: int) -> State:
    """The drive state coded in ``statusword`` (CiA 402-2 state coding)."""
    for state, (mask, value) in STATUS_CODING.items():
        if statusword & mask == value:
            return state
    raise UnknownStatusword(f"statusword 0x{statusword:04X} codes no CiA 402 state")


def encode_status(state: State, extra_bits: int = 0) -> int:
    """A statusword coding ``state`` (for the simulated drive), plus ``extra_bits``."""
    mask, value = STATUS_CODING[state]
    return (extra_bits & ~mask & 0xFFFF) | value


def decode_controlword(controlword: int, previous: int = 0) -> Command | None:
    """The command in ``controlword`` (CiA 402-2 "device control commands").

    ``previous`` is the last controlword received: fault reset is the rising edge
    of bit 7 and wins over the other bits. ``None`` if bits 0-3 code no command.
    """
    if controlword & 0x80 and not previous & 0x80:
        return Command.FAULT_RESET
    low = controlword & 0x0F
    if not low & 0x02:
        return Command.DISABLE_VOLTAGE  # xxx xx0x
    if not low & 0x04:
        return Command.QUICK_STOP  # xxx x01x
    if low & 0x07 == 0x06:
        return Command.SHUTDOWN  # xxx x110
    if low == 0x07:
        return Command.SWITCH_ON  # 0111 (also "disable operation")
    if low == 0x0F:
        return Command.ENABLE_OPERATION
    return None


def next_state(state: State, command: Command | None) -> State:
    """Drive-side reaction to ``command`` in ``state`` (unchanged if not a transition).

    SWITCH_ON and DISABLE_OPERATION share one controlword; in OPERATION ENABLED
    it means "disable operation" (transition 5).
    """
    if command is None:
        return state
    if command is Command.SWITCH_ON and state is State.OPERATION_ENABLED:
        command = Command.DISABLE_OPERATION
    return TRANSITIONS.get((state, command), (state, None))[0]


# Host-side routes: from a state, the command that moves one step toward each target.
_ROUTE = {
    S.OPERATION_ENABLED: {
        S.SWITCH_ON_DISABLED: C.SHUTDOWN,
        S.READY_TO_SWITCH_ON: C.ENABLE_OPERATION,  # transitions 3 + 4 in one command
        S.SWITCHED_ON: C.ENABLE_OPERATION,
        S.QUICK_STOP_ACTIVE: C.DISABLE_VOLTAGE,
    },
    S.SWITCHED_ON: {
        S.SWITCH_ON_DISABLED: C.SHUTDOWN,
        S.READY_TO_SWITCH_ON: C.SWITCH_ON,
        S.OPERATION_ENABLED: C.DISABLE_OPERATION,
        S.QUICK_STOP_ACTIVE: C.DISABLE_VOLTAGE,
    },
    S.READY_TO_SWITCH_ON: {
        S.SWITCH_ON_DISABLED: C.SHUTDOWN,
        S.SWITCHED_ON: C.SHUTDOWN,
        S.OPERATION_ENABLED: C.SHUTDOWN,
        S.QUICK_STOP_ACTIVE: C.DISABLE_VOLTAGE,
    },
    S.SWITCH_ON_DISABLED: {
        S.READY_TO_SWITCH_ON: C.DISABLE_VOLTAGE,
        S.SWITCHED_ON: C.DISABLE_VOLTAGE,
        S.OPERATION_ENABLED: C.DISABLE_VOLTAGE,
        S.QUICK_STOP_ACTIVE: C.DISABLE_VOLTAGE,
    },
}


class NoRoute(ValueError):
    """The host may not drive the state machine from here to there on its own."""


def command_toward(state: State, target: State) -> Command | None:
    """The one command that moves the drive a step from ``state`` toward ``target``.

    ``None`` when already there. Raises ``NoRoute`` out of FAULT, FAULT REACTION
    ACTIVE or NOT READY TO SWITCH ON (only the drive or an operator's fault reset
    leaves them), and into FAULT-type states.
    """
    if state is target:
        return None
    try:
        return _ROUTE[target][state]
    except KeyError:
        raise NoRoute(f"no host route from {state.value} to {target.value}") from None


def path(state: State, target: State) -> list[tuple[Command, State]]:
    """Commands and the states they lead to, from ``state`` to ``target``."""
    steps = []
    while state is not target:
        cmd = command_toward(state, target)
        state = next_state(state, cmd)
        steps.append((cmd, state))
        if len(steps) > len(State):
            raise NoRoute(f"route from {steps[0][1].value} to {target.value} does not converge")
    return steps
