"""The test drive's object dictionary: one description, written out as CANopenNode's
``OD.h``/``OD.c`` and as the EDS the drive serves (so the EDS is the stack's dictionary).

CANopenNode's object dictionary is C data (``301/CO_ODinterface.h``: an ``OD_t`` list of
``OD_entry_t`` sorted by index, each pointing at ``OD_obj_var_t`` / ``OD_obj_array_t`` /
``OD_obj_record_t`` descriptions of variables kept in a struct), which its editor
normally generates; ``CANopen.c`` reads the counts ``OD_CNT_*`` and the entry shortcuts
``OD_ENTRY_Hxxxx`` from ``OD.h``. The EDS is CiA 306 (INI). Objects: CiA 301
(communication) and CiA 402-2 (drive), a small torque drive as a lab's would be.

Two variants: ``event``, whose RPDO transmission type 0x1400:02 a host may set (255:
the torque applies when the RPDO arrives), and ``sync``, whose RPDOs are fixed at type 1
(read-only): CiA 301 says synchronous RPDO data take effect at the next SYNC.
"""
from __future__ import annotations

from dataclasses import dataclass

U8, I8, U16, I16, U32, I32 = 0x5, 0x2, 0x6, 0x3, 0x7, 0x4
C_TYPES = {U8: "uint8_t", I8: "int8_t", U16: "uint16_t", I16: "int16_t", U32: "uint32_t",
           I32: "int32_t"}
SIZES = {U8: 1, I8: 1, U16: 2, I16: 2, U32: 4, I32: 4}
VARIANTS = ("event", "sync")

VENDOR_ID, PRODUCT_CODE, REVISION, SERIAL = 0x4C42434E, 0x00000402, 0x00040000, 0x00000001
DEVICE_TYPE = 0x00020192  # CiA 402 (0x192), servo drive (0x02 in bits 16-23)
SUPPORTED_MODES = 1 << 9  # 0x6502: cyclic synchronous torque only (mode 10)
RATED_TORQUE_MNM = 100  # 0x6076: 1000 per-mille = 0.1 N m (1 mN at a 0.1 m lever per step)
ERROR_HISTORY = 8  # 0x1003 slots


@dataclass(frozen=True)
class Var:
    """One sub-index. ``node_id``: the default is ``$NODEID`` + ``default`` (CANopenNode
    keeps the base in the dictionary and adds the node id itself)."""

    sub: int
    name: str
    dtype: int
    access: str  # ro, rw, const
    default: int = 0
    pdo: bool = False
    node_id: bool = False


@dataclass(frozen=True)
class Obj:
    index: int
    name: str
    kind: str  # var, array, record
    subs: tuple

    @property
    def cname(self) -> str:
        return f"x{self.index:04X}"


def var(index, name, dtype, access, default=0, pdo=False, node_id=False) -> Obj:
    return Obj(index, name, "var", (Var(0, name, dtype, access, default, pdo, node_id),))


def array(index, name, count_access, dtype, access, values, count=None) -> Obj:
    """CiA 301 ARRAY: sub-index 0 holds the count (``count``, default the number of
    elements), 1..n share one type and access."""
    subs = [Var(0, "Highest sub-index supported" if count is None else "Number of entries", U8,
                count_access, len(values) if count is None else count)]
    subs += [Var(k, f"{name} {k}", dtype, access, v) for k, v in enumerate(values, 1)]
    return Obj(index, name, "array", tuple(subs))


def record(index, name, members) -> Obj:
    """CiA 301 RECORD; sub-index 0 is the highest sub-index unless ``members`` give it (the
    number of mapped objects of a PDO mapping)."""
    subs = [] if members[0].sub == 0 else [
        Var(0, "Highest sub-index supported", U8, "const", max(m.sub for m in members))]
    return Obj(index, name, "record", tuple(subs + list(members)))


def _pdos(variant: str) -> list[Obj]:
    """Two RPDOs and two TPDOs of four mapping slots. PDO 1 comes mapped (controlword in,
    statusword out, as drives ship); PDO 2 is off (COB-ID bit 31) and empty."""
    fixed = variant == "sync"
    out = []
    for n in range(2):
        off = 0x80000000 if n else 0
        out.append(record(0x1400 + n, f"RPDO{n + 1} communication parameter", [
            Var(1, "COB-ID used by RPDO", U32, "rw", off | (0x200 + 0x100 * n), node_id=True),
            Var(2, "Transmission type", U8, "ro" if fixed else "rw", 1 if fixed else 255),
            Var(3, "Inhibit time", U16, "rw"),
            Var(5, "Event timer", U16, "rw")]))
    for n in range(2):
        out.append(record(0x1600 + n, f"RPDO{n + 1} mapping parameter",
                          [Var(0, "Number of mapped objects", U8, "rw", 0 if n else 1)]
                          + [Var(k, f"Mapping entry {k}", U32, "rw",
                                 0x60400010 if (n, k) == (0, 1) else 0) for k in range(1, 5)]))
    for n in range(2):
        off = 0x80000000 if n else 0
        out.append(record(0x1800 + n, f"TPDO{n + 1} communication parameter", [
            Var(1, "COB-ID used by TPDO", U32, "rw", off | (0x180 + 0x100 * n), node_id=True),
            Var(2, "Transmission type", U8, "rw", 254),
            Var(3, "Inhibit time", U16, "rw"),
            Var(5, "Event timer", U16, "rw"),
            Var(6, "SYNC start value", U8, "rw")]))
    for n in range(2):
        out.append(record(0x1A00 + n, f"TPDO{n + 1} mapping parameter",
                          [Var(0, "Number of mapped objects", U8, "rw", 0 if n else 1)]
                          + [Var(k, f"Mapping entry {k}", U32, "rw",
                                 0x60410010 if (n, k) == (0, 1) else 0) for k in range(1, 5)]))
    return out


def objects(variant: str) -> list[Obj]:
    """The dictionary of ``variant``, sorted by index."""
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    objs = [
        var(0x1000, "Device type", U32, "ro", DEVICE_TYPE),
        var(0x1001, "Error register", U8, "ro", 0, pdo=True),
        array(0x1003, "Pre-defined error field", "rw", U32, "ro", [0] * ERROR_HISTORY, count=0),
        var(0x1005, "COB-ID SYNC message", U32, "rw", 0x80),
        var(0x1006, "Communication cycle period", U32, "rw", 0),
        var(0x100C, "Guard time", U16, "rw", 0),
        var(0x100D, "Life time factor", U8, "rw", 0),
        var(0x1014, "COB-ID EMCY", U32, "ro", 0x80, node_id=True),
        array(0x1016, "Consumer heartbeat time", "const", U32, "rw", [0]),
        var(0x1017, "Producer heartbeat time", U16, "rw", 0),
        record(0x1018, "Identity object", [
            Var(1, "Vendor-ID", U32, "ro", VENDOR_ID),
            Var(2, "Product code", U32, "ro", PRODUCT_CODE),
            Var(3, "Revision number", U32, "ro", REVISION),
            Var(4, "Serial number", U32, "ro", SERIAL)]),
        *_pdos(variant),
        var(0x603F, "Error code", U16, "ro", 0, pdo=True),
        var(0x6007, "Abort connection option code", I16, "rw", 1),
        var(0x6040, "Controlword", U16, "rw", 0, pdo=True),
        var(0x6041, "Statusword", U16, "ro", 0, pdo=True),
        var(0x605A, "Quick stop option code", I16, "rw", 2),
        var(0x605E, "Fault reaction option code", I16, "rw", 2),
        var(0x6060, "Modes of operation", I8, "rw", 0, pdo=True),
        var(0x6061, "Modes of operation display", I8, "ro", 0, pdo=True),
        var(0x6064, "Position actual value", I32, "ro", 0, pdo=True),
        var(0x606C, "Velocity actual value", I32, "ro", 0, pdo=True),
        var(0x6071, "Target torque", I16, "rw", 0, pdo=True),
        var(0x6072, "Max torque", U16, "rw", 1000, pdo=True),
        var(0x6076, "Motor rated torque", U32, "ro", RATED_TORQUE_MNM),
        var(0x6077, "Torque actual value", I16, "ro", 0, pdo=True),
        var(0x6502, "Supported drive modes", U32, "ro", SUPPORTED_MODES),
    ]
    return sorted(objs, key=lambda o: o.index)


# ------------------------------------------------------------------ C (CANopenNode)
def _attr(v: Var) -> str:
    """CANopenNode attribute bits (``OD_attributes_t``)."""
    bits = ["ODA_SDO_RW" if v.access == "rw" else "ODA_SDO_R"]
    if v.pdo:
        bits.append("ODA_TRPDO" if v.access == "rw" else "ODA_TPDO")
    if SIZES[v.dtype] > 1:
        bits.append("ODA_MB")
    return " | ".join(bits)


def _member(o: Obj) -> list[str]:
    """The object's variables as members of ``OD_RAM_t``."""
    if o.kind == "var":
        return [f"    {C_TYPES[o.subs[0].dtype]} {o.cname};"]
    if o.kind == "array":
        return [f"    uint8_t {o.cname}_sub0;",
                f"    {C_TYPES[o.subs[1].dtype]} {o.cname}[{len(o.subs) - 1}];"]
    inner = " ".join(f"{C_TYPES[v.dtype]} sub{v.sub};" for v in o.subs)
    return [f"    struct {{ {inner} }} {o.cname};"]


def _value(o: Obj) -> str:
    if o.kind == "var":
        return f"    .{o.cname} = {o.subs[0].default},"
    if o.kind == "array":
        values = ", ".join(str(v.default) for v in o.subs[1:])
        return f"    .{o.cname}_sub0 = {o.subs[0].default},\n    .{o.cname} = {{{values}}},"
    inner = ", ".join(f".sub{v.sub} = 0x{v.default:X}" for v in o.subs)
    return f"    .{o.cname} = {{{inner}}},"


def _description(o: Obj) -> tuple[str, str]:
    """(declaration, initialiser) of the object's constant description."""
    if o.kind == "var":
        v = o.subs[0]
        return (f"    OD_obj_var_t o_{o.index:04X};",
                f"    .o_{o.index:04X} = {{.dataOrig = &OD_RAM.{o.cname}, .attribute = {_attr(v)}, "
                f".dataLength = {SIZES[v.dtype]}}},")
    if o.kind == "array":
        v0, v = o.subs[0], o.subs[1]
        return (f"    OD_obj_array_t o_{o.index:04X};",
                f"    .o_{o.index:04X} = {{.dataOrig0 = &OD_RAM.{o.cname}_sub0, "
                f".dataOrig = &OD_RAM.{o.cname}[0], .attribute0 = {_attr(v0)}, "
                f".attribute = {_attr(v)}, .dataElementLength = {SIZES[v.dtype]}, "
                f".dataElementSizeof = sizeof({C_TYPES[v.dtype]})}},")
    subs = ",\n".join(f"        {{.dataOrig = &OD_RAM.{o.cname}.sub{v.sub}, .subIndex = {v.sub}, "
                      f".attribute = {_attr(v)}, .dataLength = {SIZES[v.dtype]}}}" for v in o.subs)
    return (f"    OD_obj_record_t o_{o.index:04X}[{len(o.subs)}];",
            f"    .o_{o.index:04X} = {{\n{subs}\n    }},")


_ODT = {"var": "ODT_VAR", "array": "ODT_ARR", "record": "ODT_REC"}


def od_h(variant: str) -> str:
    objs = objects(variant)
    n_rpdo = sum(1 for o in objs if 0x1400 <= o.index < 0x1600)
    n_tpdo = sum(1 for o in objs if 0x1800 <= o.index < 0x1A00)
    lines = ["/* Written by tests/canopennode/dictionary.py: the labbench test drive's dictionary"
             f" ({variant} variant). */",
             "#ifndef OD_H", "#define OD_H", "",
             # CANopen.c's object counts (one NMT, EMCY, SYNC consumer, HB consumer, ...)
             "#define OD_CNT_NMT 1", "#define OD_CNT_EM 1", "#define OD_CNT_SYNC 1",
             "#define OD_CNT_EM_PROD 1", "#define OD_CNT_HB_CONS 1", "#define OD_CNT_HB_PROD 1",
             f"#define OD_CNT_RPDO {n_rpdo}", f"#define OD_CNT_TPDO {n_tpdo}",
             f"#define OD_CNT_ARR_1003 {ERROR_HISTORY}", "#define OD_CNT_ARR_1016 1", "",
             "typedef struct {"]
    for o in objs:
        lines += _member(o)
    lines += ["} OD_RAM_t;", "", "extern OD_RAM_t OD_RAM;", "extern OD_t* OD;", ""]
    lines += [f"#define OD_ENTRY_H{o.index:04X} (&OD->list[{k}])" for k, o in enumerate(objs)]
    lines += ["", "#endif", ""]
    return "\n".join(lines)


def od_c(variant: str) -> str:
    objs = objects(variant)
    decls, inits = zip(*(_description(o) for o in objs))
    entries = [f"    {{0x{o.index:04X}, {len(o.subs)}, {_ODT[o.kind]}, &ODObjs.o_{o.index:04X}, "
               "NULL},"
               for o in objs]
    return "\n".join([
        "/* Written by tests/canopennode/dictionary.py: the labbench test drive's dictionary"
        f" ({variant} variant). */",
        "#define OD_DEFINITION", '#include "301/CO_ODinterface.h"', '#include "OD.h"', "",
        "OD_RAM_t OD_RAM = {", *(_value(o) for o in objs), "};", "",
        "typedef struct {", *decls, "} ODObjs_t;", "",
        "static CO_PROGMEM ODObjs_t ODObjs = {", *inits, "};", "",
        "static OD_entry_t ODList[] = {", *entries, "    {0x0000, 0x00, 0, NULL, NULL}", "};", "",
        "static OD_t ODBase = {(sizeof(ODList) / sizeof(ODList[0])) - 1, &ODList[0]};",
        "OD_t* OD = &ODBase;", ""])


# ------------------------------------------------------------------ EDS (CiA 306)
def _eds_value(v: Var) -> str:
    if v.node_id:
        return f"$NODEID+0x{v.default:X}"
    if v.dtype in (I8, I16, I32):
        return str(v.default)
    return f"0x{v.default:X}"


def eds(variant: str) -> str:
    objs = objects(variant)
    mandatory = [o for o in objs if o.index in (0x1000, 0x1001, 0x1018)]
    optional = [o for o in objs if o not in mandatory]
    n_rpdo = sum(1 for o in objs if 0x1400 <= o.index < 0x1600)
    n_tpdo = sum(1 for o in objs if 0x1800 <= o.index < 0x1A00)
    out = ["[FileInfo]", f"FileName=canopennode-{variant}.eds", "EDSVersion=4.0",
           f"Description=labbench test drive on CANopenNode v4 ({variant} RPDOs), written by "
           "tests/canopennode/dictionary.py", "CreatedBy=labbench", "",
           "[DeviceInfo]", "VendorName=labbench tests", f"VendorNumber=0x{VENDOR_ID:08X}",
           "ProductName=CiA 402 torque drive on CANopenNode",
           f"ProductNumber=0x{PRODUCT_CODE:08X}", f"RevisionNumber=0x{REVISION:08X}",
           "BaudRate_1000=1", "SimpleBootUpSlave=1", "Granularity=8",
           f"NrOfRXPDO={n_rpdo}", f"NrOfTXPDO={n_tpdo}", "LSS_Supported=0", ""]
    for title, group in (("MandatoryObjects", mandatory), ("OptionalObjects", optional)):
        out += [f"[{title}]", f"SupportedObjects={len(group)}"]
        out += [f"{k}=0x{o.index:04X}" for k, o in enumerate(group, 1)] + [""]
    out += ["[ManufacturerObjects]", "SupportedObjects=0", ""]
    for o in objs:
        if o.kind != "var":
            out += [f"[{o.index:04X}]", f"ParameterName={o.name}",
                    f"ObjectType={'0x8' if o.kind == 'array' else '0x9'}",
                    f"SubNumber={len(o.subs)}", ""]
        for v in o.subs:
            out += [f"[{o.index:04X}]" if o.kind == "var" else f"[{o.index:04X}sub{v.sub:X}]",
                    f"ParameterName={v.name}", "ObjectType=0x7", f"DataType=0x{v.dtype:04X}",
                    f"AccessType={v.access}", f"DefaultValue={_eds_value(v)}",
                    f"PDOMapping={int(v.pdo)}", ""]
    return "\n".join(out)
