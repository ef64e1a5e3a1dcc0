"""Reference pages generated from the code, so they cannot drift from it.

Each function returns one page as Markdown, read from the place the program itself reads:

* ``cli_page``: every verb and option, walked from the argparse parsers ``canical`` builds;
* ``frames_page``: every CAN frame and signal, from ``dbc/canical.dbc`` through cantools;
* ``object_dictionary_page``: the IMU's objects, from the EDS through canopen;
* ``configuration_page``: the daemon's keys, from the table in :mod:`config_keys`, checked
  against what the configuration parser accepts (a key it accepts and the table lacks fails);
* ``set_file_page``: the coefficient set file, from the table in :mod:`set_schema` and the
  term kinds the set loader knows;
* ``packages.page``: the package's rings and modules, from the import graph the ring test reads.

The MkDocs hook (``docs/hooks/generate.py``) calls :func:`pages` at build time; run this file
to write the pages into a folder instead: ``python docs/scripts/reference.py --out DIR``.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import config_keys  # noqa: E402
import packages  # noqa: E402
import set_schema  # noqa: E402

GENERATED_NOTE = (
    '!!! note "Generated"\n    This page is generated from {source} when the documentation is built; '
    "edit the source, not the page.\n"
)


def cell(text: object) -> str:
    """A value as a Markdown table cell: pipes escaped, newlines folded."""
    return " ".join(str(text).split()).replace("|", "\\|")


def code(text: object) -> str:
    return f"`{text}`" if str(text) != "" else ""


# --- the command line -----------------------------------------------------------------------------


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _option_rows(parser: argparse.ArgumentParser) -> Iterator[str]:
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction | argparse._SubParsersAction):
            continue
        if action.option_strings:
            names = ", ".join(action.option_strings)
            takes = action.nargs != 0
            metavar = action.metavar or (action.dest.upper() if takes else "")
            if isinstance(metavar, tuple):
                metavar = " ".join(metavar)
            usage = f"{names} {metavar}".strip() if takes else names
        else:
            usage = str(action.metavar or action.dest)
            if action.nargs in ("+", "*"):
                usage += " …"
        default = action.default
        if default in (None, False, argparse.SUPPRESS) or not action.option_strings:
            default_text = ""
        else:
            default_text = code(default)
        choices = f" (one of {', '.join(map(str, action.choices))})" if action.choices else ""
        required = " **required**" if getattr(action, "required", False) and action.option_strings else ""
        yield f"| {code(cell(usage))} | {default_text} | {cell(action.help or '')}{choices}{required} |"


def _command_section(path: str, parser: argparse.ArgumentParser, level: int) -> list[str]:
    usage = " ".join(parser.format_usage().split())
    usage = usage.removeprefix("usage: ")
    lines = [f"{'#' * level} canical {path}", "", f"```\n{usage}\n```", ""]
    if parser.description:
        lines += [parser.description.strip(), ""]
    rows = list(_option_rows(parser))
    if rows:
        lines += ["| argument | default | meaning |", "|---|---|---|", *rows, ""]
    for name, child in _subparsers(parser).items():
        lines += _command_section(f"{path} {name}", child, level + 1)
    return lines


def cli_page() -> str:
    from canical.commands import COMMANDS
    from canical.commands.cli import build_parser

    parser = build_parser(None)
    commands = _subparsers(parser)
    lines = ["# Command line", "", GENERATED_NOTE.format(source="the argument parsers of `canical`"), ""]
    lines += ["| command | what it does |", "|---|---|"]
    lines += [f"| [`{name}`](#canical-{name}) | {cell(text)} |" for name, text in COMMANDS.items()]
    lines += [
        "",
        "Every command exits with status 0 on success and prints an error a user can act on as "
        "one line with status 2 (`calibrate --strict`: 3 when the residual stays unexplained).",
        "",
    ]
    for name in COMMANDS:
        lines += _command_section(name, commands[name], 2)
    return "\n".join(lines) + "\n"


# --- CAN frames -----------------------------------------------------------------------------------


def frames_page(dbc_path: Path | None = None) -> str:
    import cantools

    path = dbc_path or ROOT / "dbc" / "canical.dbc"
    db = cantools.database.load_file(str(path), strict=False)
    lines = ["# CAN frames", "", GENERATED_NOTE.format(source="`dbc/canical.dbc` (read with cantools)"), ""]
    lines += [
        "The DBC is the one source of frame layouts: the daemon, the recorder, the emulated IMU "
        "and the codecs generated at start all read it. Signals are little-endian (Intel) "
        "unless the table says otherwise; *physical value = raw × scale + offset*.",
        "",
    ]
    lines += ["| frame | id | bytes | sent by | what it is |", "|---|---|---|---|---|"]
    for m in db.messages:
        lines.append(
            f"| [{m.name}](#{m.name.lower()}) | `0x{m.frame_id:03X}` | {m.length} | "
            f"{', '.join(m.senders)} | {cell(m.comment or '')} |"
        )
    lines.append("")
    for m in db.messages:
        lines += [
            f"## {m.name}",
            "",
            f"Id `0x{m.frame_id:03X}`, {m.length} bytes, sent by "
            f"{', '.join(m.senders) or 'any node'}"
            f"{', multiplexed' if m.is_multiplexed() else ''}.",
            "",
        ]
        if m.comment:
            lines += [m.comment, ""]
        lines += [
            "| signal | bits | signed | scale | offset | range | unit | page | meaning |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for s in m.signals:
            bits = f"{s.start}+{s.length}" + ("" if s.byte_order == "little_endian" else " (big-endian)")
            page = "mux" if s.is_multiplexer else ", ".join(map(str, s.multiplexer_ids or []))
            meaning = s.comment or ""
            if s.choices:
                meaning += " " + ", ".join(f"{k} {v}" for k, v in s.choices.items())
            known = s.minimum is not None and s.maximum is not None
            span = f"{s.minimum:g} … {s.maximum:g}" if known else ""
            signed = "yes" if s.is_signed else "no"
            lines.append(
                f"| `{s.name}` | {bits} | {signed} | {s.scale:g} | {s.offset:g} | {span} | "
                f"{s.unit or ''} | {page} | {cell(meaning)} |"
            )
        lines.append("")
    return "\n".join(lines)


# --- the object dictionary ------------------------------------------------------------------------

DATA_TYPES = {
    1: "BOOLEAN",
    2: "INTEGER8",
    3: "INTEGER16",
    4: "INTEGER32",
    5: "UNSIGNED8",
    6: "UNSIGNED16",
    7: "UNSIGNED32",
    8: "REAL32",
    9: "VISIBLE_STRING",
    10: "OCTET_STRING",
    15: "DOMAIN",
    17: "REAL64",
    21: "INTEGER64",
    27: "UNSIGNED64",
}


def _od_row(index: str, sub: str, var) -> str:
    default = var.default
    if isinstance(default, bytes | bytearray):
        default = f"{len(default)} bytes"
    elif var.data_type in (5, 6, 7) and isinstance(default, int) and default > 9:
        default = f"0x{default:X}"
    return (
        f"| {index} | {sub} | {cell(var.name)} | {DATA_TYPES.get(var.data_type, var.data_type)} | "
        f"{var.access_type} | {cell('' if default is None else default)} | {cell(var.description or '')} |"
    )


def object_dictionary_page(node_id: int = 0x10) -> str:
    import canopen

    from canical.frames.imu_dictionary import eds_path

    od = canopen.import_od(str(eds_path()), node_id)
    lines = [
        "# Object dictionary",
        "",
        GENERATED_NOTE.format(source="the IMU's EDS (`canical/data/canical-imu.eds`, read with canopen)"),
        "",
        f"Values for node id `0x{node_id:02X}`. `push`, `pull`, `export dcf` and the daemon's "
        "`device:` source use these objects: they need an IMU that runs canical's firmware "
        "(or implements this dictionary). The rules the device follows are in "
        "`services/canical-imu.md`.",
        "",
        "| index | sub | name | type | access | default | notes |",
        "|---|---|---|---|---|---|---|",
    ]
    for obj in od.values():
        index = f"`0x{obj.index:04X}`"
        if isinstance(obj, canopen.objectdictionary.ODVariable):
            lines.append(_od_row(index, "", obj))
            continue
        lines.append(f"| {index} | | **{cell(obj.name)}** | {type(obj).__name__[2:].lower()} | | | |")
        for var in obj.values():
            lines.append(_od_row("", str(var.subindex), var))
    return "\n".join(lines) + "\n"


# --- the daemon's configuration -------------------------------------------------------------------


def configuration_page() -> str:
    missing, stale = config_keys.undocumented_keys()
    if missing or stale:
        raise RuntimeError(
            f"docs/scripts/config_keys.py is out of step with canical/bus/daemon_config.py: "
            f"accepted but not documented {sorted(missing)}; documented but refused {sorted(stale)}"
        )
    lines = [
        "# Daemon configuration",
        "",
        GENERATED_NOTE.format(
            source="the key table in `docs/scripts/config_keys.py`, checked "
            "against the keys `canical/bus/daemon_config.py` accepts"
        ),
        "",
        config_keys.INTRODUCTION,
        "",
        "| key | default | checked | meaning |",
        "|---|---|---|---|",
    ]
    for key in config_keys.KEYS:
        lines.append(f"| `{key.key}` | {cell(key.default)} | {cell(key.check)} | {cell(key.meaning)} |")
    example = (ROOT / "services" / "canical-can0.yaml").read_text(encoding="utf-8")
    lines += [
        "",
        "## The deployable example",
        "",
        "`services/canical-can0.yaml`, which `canical install-service` copies to `/etc/canical/can0.yaml`:",
        "",
        "```yaml",
        example.rstrip(),
        "```",
        "",
    ]
    return "\n".join(lines)


# --- the coefficient set file ---------------------------------------------------------------------


def set_file_page() -> str:
    from canical.sets.coefficients import SCHEMA_VERSION
    from canical.sets.terms import FEATURES, FORMS

    lines = [
        "# Coefficient set file",
        "",
        GENERATED_NOTE.format(
            source="the field table in `docs/scripts/set_schema.py` (a test holds it "
            "to the sets canical writes) and the term kinds `canical/sets/terms.py` "
            "accepts"
        ),
        "",
        set_schema.INTRODUCTION.format(schema=SCHEMA_VERSION),
        "",
        "| field | type | meaning |",
        "|---|---|---|",
    ]
    for f in set_schema.FIELDS:
        lines.append(f"| `{f.path}` | {cell(f.type)} | {cell(f.meaning)} |")
    lines += [
        "",
        "## Effect terms",
        "",
        set_schema.TERMS_INTRODUCTION,
        "",
        "| kind | features | forms |",
        "|---|---|---|",
    ]
    for kind, features in FEATURES.items():
        lines.append(
            f"| `{kind}` | {', '.join(f'`{f}`' for f in features)} | {', '.join(f'`{f}`' for f in FORMS)} |"
        )
    lines += ["", set_schema.EXAMPLE_INTRO, "", "```yaml", set_schema.example_text().rstrip(), "```", ""]
    return "\n".join(lines)


def pages() -> dict[str, str]:
    """Every generated page, by its path under ``docs/``."""
    return {
        "reference/cli.md": cli_page(),
        "reference/configuration.md": configuration_page(),
        "reference/set-file.md": set_file_page(),
        "reference/frames.md": frames_page(),
        "reference/object-dictionary.md": object_dictionary_page(),
        "reference/packages.md": packages.page(),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder to write the pages into")
    args = parser.parse_args()
    for rel, text in pages().items():
        path = args.out / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
