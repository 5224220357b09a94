"""EDS/DCF values read by data type (CiA 306 number forms, CiA 301 types)."""
import pytest

from labbench.drivers.eds_values import neutral, parse

I8, I16, I32, U8, U16, U32, I64, U64 = 0x2, 0x3, 0x4, 0x5, 0x6, 0x7, 0x15, 0x1B


@pytest.mark.parametrize("text,dtype,value", [
    ("0xFFFF8000", I32, -32768), ("0x80000000", I32, -2147483648), ("0x7FFFFFFF", I32, 2**31 - 1),
    ("0xFFFF", I16, -1), ("0xFD", I8, -3), ("-3", I8, -3), ("-0x10", I16, -16),
    ("0xFFFFFFFF", U32, 2**32 - 1), ("0xffffffffffffffff", I64, -1), ("017", U8, 15),
    ("0", U8, 0), ("00", U8, 0), ("+12", U16, 12), ("$NODEID+0x180", U32, 0x185),
    ("0x200 + $NODEID", U32, 0x205), ("$nodeid+512", U16, 517), ("0X1F", U64, 31),
    ("0x8000", I32, 32768),  # fits the type as written: not a bit pattern
])
def test_values_by_type(text, dtype, value):
    assert parse(text, dtype, node_id=5) == value


@pytest.mark.parametrize("text,dtype,why", [
    ("0x1FFFF", U16, "outside the range"), ("-1", U32, "outside the range"),
    ("128", I8, "outside the range"), ("-0x81", I8, "outside the range"),
    ("08", U8, "not a number"), ("1.5", U16, "not a number"), ("abc", U32, "not a number"),
    ("$NODEID+1", U8, "without a node id"),
])
def test_values_refused_with_the_reason(text, dtype, why):
    with pytest.raises(ValueError, match=why):
        parse(text, dtype, node_id=None if "NODEID" in text else 1)


def test_other_types_and_neutral_values():
    assert parse("1.25", 0x8) == 1.25 and parse("drive x", 0x9) == "drive x"
    assert parse("0a 0B", 0xA) == b"\x0a\x0b"
    assert [neutral(t) for t in (U32, I8, 0x8, 0x9, 0xF)] == [0, 0, 0.0, "", b""]
