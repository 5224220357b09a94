"""The CiA 402 torque drive on CANopenNode v4, the most used open-source CiA 301 slave stack.

The drive is built from ``../shared/third_party/CANopenNode`` with our object dictionary,
transport and application (``tests/canopennode``) and runs as a process of its own on
python-can's ``udp_multicast``. Here: the drive alone, through canopen's own SDO client,
against the EDS it serves and what CiA 301 says the stack answers.
"""
import pytest

import canopennode
from canopennode import build, dictionary
from test_canopen_process import _children

# Lock-step runs on a shared machine: the drive's monitors (wall clock, in its own process)
# and the loop's watchdog well above a loaded machine's stalls; the tests of the monitors
# set their own.
CALM = {"safety": {"watchdog_s": 2.0},
        "canopen": {"heartbeat_consumer_ms": 1000, "rpdo_timeout_ms": 500,
                    "life_time_factor": 50, "sdo_timeout_s": 2.0}}


@pytest.fixture(scope="module", autouse=True)
def stack():
    """Both variants built once (cached across runs); a missing stack is one clear line."""
    try:
        return {v: build.build(v) for v in dictionary.VARIANTS}
    except build.StackMissing as exc:
        pytest.fail(str(exc), pytrace=False)


@pytest.fixture(autouse=True)
def no_process_left():
    before = _children()
    yield
    assert _children() - before == set(), "a drive process outlived its test"


@pytest.fixture
def drive():
    """Factory: a running CANopenNode drive (``canopennode.start``); all closed after."""
    started = []

    def make(variant="event", tables=None, **kw):
        merged = {k: {**CALM.get(k, {}), **(tables or {}).get(k, {})}
                  for k in {*CALM, *(tables or {})}}
        started.append(canopennode.start(variant, merged, **kw))
        return started[-1]

    yield make
    for r in started:
        r.close()


# -------------------------------------------------------------- the drive as built
def test_the_drive_serves_its_eds_and_the_stack_answers_as_cia_301_says(drive):
    """Every object of the served EDS reads back its default over SDO (canopen's own client
    on the bus); the stack's own answers: 0x1003 above its count is abort 0x08000024,
    a read-only object refuses a write (0x06010002), a mode 0x6502 lacks is 0x06090030."""
    import canopen
    from canopen.objectdictionary import ODVariable

    r = drive("sync")
    net = canopen.Network(r.monitor)
    node = canopen.RemoteNode(1, str(r.eds))
    net.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = 2.0
    r.notifier.add_listener(net.listeners[0])
    try:
        for obj in node.object_dictionary.values():
            for v in [obj] if isinstance(obj, ODVariable) else obj.values():
                if v.index == 0x1003 and v.subindex > 0:
                    with pytest.raises(canopen.SdoAbortedError) as info:
                        node.sdo.upload(v.index, v.subindex)
                    assert info.value.code == 0x08000024  # no error yet: no data
                    continue
                if v.index in (0x6041, 0x6061):  # the application's live values
                    continue
                assert v.decode_raw(node.sdo.upload(v.index, v.subindex)) == v.default, \
                    f"0x{v.index:04X}:{v.subindex:02X}"
        for index, sub, raw in ((0x1400, 2, b"\xff"), (0x6502, 0, bytes(4)), (0x1018, 1, bytes(4))):
            with pytest.raises(canopen.SdoAbortedError) as info:
                node.sdo.download(index, sub, raw)
            assert info.value.code == 0x06010002, (hex(index), sub)  # read-only
        with pytest.raises(canopen.SdoAbortedError) as info:
            node.sdo.download(0x6060, 0, b"\x04")  # profile torque: 0x6502 offers CST only
        assert info.value.code == 0x06090030
        node.sdo.download(0x6060, 0, b"\x0a")
        assert node.sdo.upload(0x6061, 0) == b"\x0a"
        node.sdo.download(0x6040, 0, b"\x06\x00")  # shutdown: READY TO SWITCH ON
        assert int.from_bytes(node.sdo.upload(0x6041, 0), "little") & 0x6F == 0x21
    finally:
        r.notifier.remove_listener(net.listeners[0])
