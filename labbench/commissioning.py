"""What a commissioning run changes outside itself: the rendering gate and ``--write-rig``.

The gate (issue 20): until a rig has passed ``labbench run commission``'s direction check
(``[rig] direction_checked``, written by ``--write-rig``), a run on real hardware refuses
a VE with K > 0 or B > 0: a flipped sign turns a spring into positive feedback. The
simulators need no gate; ``--skip-commissioning`` is for people who know their rig.

``write_rig`` (and ``write_tables``, for any table: the timing preflight's limits) puts a
commissioning result's ``changes`` into the rig file with
``tomlkit``, which keeps the user's comments and layout, after copying the old file
to ``<name>.bak`` (an existing backup is replaced: it is the file as it was just now),
both through ``labbench.safe_write.edit_text`` (never through a planted link, mode and
line breaks kept).
"""
from __future__ import annotations

from pathlib import Path

from labbench.errors import UserError

# the [rig] fields a commissioning run may write
WRITABLE = ("position_sign", "measured_td_s", "measured_td_from", "direction_checked")


# what to do about the gate, in the command line's words (the window names its own controls)
CLI_REMEDY = "run `labbench run commission --rig FILE --write-rig` first (or --skip-commissioning)"


def gate(ves, rig, simulated: bool, skip: bool = False, remedy: str = CLI_REMEDY,
         where: str | None = None) -> None:
    """One UserError when real hardware would render a spring or damper before the rig
    passed its direction check (module doc); ``ves``: every VE the run will render;
    ``remedy``: what the message says to do; ``where``: the rig named (default its source)."""
    if simulated or skip or rig.direction_checked:
        return
    for ve in ves:
        if ve.K > 0 or ve.B > 0:
            raise UserError(f"{where or rig.source}: this rig has not passed its direction check: "
                            f"refusing K = {ve.K:g} N/m, B = {ve.B:g} N s/m on real hardware; "
                            f"{remedy}")


def changes_to_write(results: dict, session: str, when: str) -> dict:
    """The [rig] fields a commissioning result calls for, with where they came from; the
    direction stamp only when the direction check passed."""
    out = {k: v for k, v in (results.get("changes") or {}).items() if k in WRITABLE}
    if "measured_td_s" in out:
        out["measured_td_from"] = f"labbench run commission, {session}"
    direction = results.get("direction") or {}
    if not direction.get("flipped", True) and (direction.get("verdict") or {}).get("level") == "ok":
        out["direction_checked"] = f"{when}, {session}"
    return out


def write_rig(path, fields: dict) -> Path | None:
    """Set ``fields`` in the ``[rig]`` table of the rig file ``path`` (``write_tables``)."""
    return write_tables(path, {"rig": fields})


def write_tables(path, tables: dict) -> Path | None:
    """Set ``{table: {field: value}}`` in the rig file ``path`` (comments, layout, line
    breaks and mode kept; a link is edited at its real path, as an editor does); the old
    file goes to ``<real name>.bak`` first (``labbench.safe_write.edit_text``). Returns
    the backup's path, or None when nothing changed. One UserError when the file cannot be
    read or written safely (read-only, a read-only folder, a full disk)."""
    import tomlkit

    from labbench.safe_write import edit_text

    tables = {name: fields for name, fields in tables.items() if fields}

    def change(text: str) -> str | None:
        try:
            doc = tomlkit.parse(text)
        except tomlkit.exceptions.ParseError as exc:
            raise UserError(f"{path}: not valid TOML: {exc}") from None
        if all(doc.get(t) is not None and all(doc[t].get(k) == v for k, v in f.items())
               for t, f in tables.items()):
            return None
        for name, fields in tables.items():
            if doc.get(name) is None:
                doc[name] = tomlkit.table()
            for k, v in fields.items():
                doc[name][k] = v
        return tomlkit.dumps(doc)

    return edit_text(path, change, "rig file").backup
