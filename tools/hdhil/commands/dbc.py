"""``hdhil dbc export OUT.dbc``: one CAN database for a whole trace.

A trace holds two buses: the control bus (``control.dbc``, 11-bit identifiers) and the
emulator's ground truth (``truth.dbc``, 29-bit identifiers).  Tools that take one
database per decode (``cantools decode``, ``cantools plot``, CANalyzer, asammdf's bus
logging export) report every truth frame as unknown when given only the control bus's.
This command writes both as one DBC: every message with its signals, units, value
tables, comments and attributes (cycle times, send types, the CANopen object kind, the
node-IDs and the bus's bit rate), the nodes of both.  The identifiers never collide
(11-bit against 29-bit), so one database decodes every frame.  The shipped files stay
the source; the merged one is made from them each time.  With ``--mapping NAME`` the
drive's PDO messages are those of a shipped mapping (e.g. ``cst-sensor``: DRIVE_TPDO1
carries 0x6077, 0x6064 and the joint-torque sensor 0x2102), built from its DCF and the
drive's EDS (:func:`hdhil.canopen.mapping.mapping_database`), as ``hdhil dump`` decodes
a trace of that mapping.
"""

from __future__ import annotations

import argparse
from collections import OrderedDict
from pathlib import Path
from typing import Any

from hdhil.core.errors import UserError
from hdhil.core.files import atomic_path, check_not_inputs, check_output


def merged_database(mapping: str = "raw") -> Any:
    """The control and truth databases as one :class:`cantools.database.can.Database`,
    the drive's PDOs as the shipped ``mapping`` configures them."""
    import copy

    import cantools
    from cantools.database.can import Database
    from cantools.database.can.formats.dbc.dbc_specifics import DbcSpecifics

    from hdhil.canopen.mapping import mapping_database
    from hdhil.dbc import dbc_path

    control = (
        cantools.database.load_file(str(dbc_path("control")))
        if mapping == "raw"
        else copy.deepcopy(mapping_database(mapping))
    )
    truth = cantools.database.load_file(str(dbc_path("truth")))
    definitions: OrderedDict[str, Any] = OrderedDict(control.dbc.attribute_definitions)
    for name, definition in truth.dbc.attribute_definitions.items():
        definitions.setdefault(name, definition)
    value_tables = OrderedDict(control.dbc.value_tables)
    value_tables.update(truth.dbc.value_tables)
    nodes = list(control.nodes)
    names = {n.name for n in nodes}
    nodes += [n for n in truth.nodes if n.name not in names]
    specifics = DbcSpecifics(
        attributes=control.dbc.attributes,
        attribute_definitions=definitions,
        environment_variables=control.dbc.environment_variables,
        value_tables=value_tables,
    )
    return Database(
        messages=[*control.messages, *truth.messages],
        nodes=nodes,
        buses=control.buses,
        version=control.version,
        dbc_specifics=specifics,
        strict=True,
    )


def merged_dbc_text(mapping: str = "raw", drive_node_id: int = 2) -> str:
    """The merged database as DBC text, checked by loading it back; with the drive at
    another node-ID than 2, rigdb's database of that layout
    (:func:`hdhil.canopen.rigdb.rig_databases`, the same messages at the drive's
    identifiers)."""
    import cantools

    if drive_node_id == 2:
        db = merged_database(mapping)
    else:
        from hdhil.canopen.rigdb import RigDrive, rig_databases

        db = rig_databases([RigDrive("", drive_node_id, mapping=mapping)])["control"]
    text = db.as_dbc_string()
    cantools.database.load_string(text, database_format="dbc", strict=True)
    return text


def export(out: Path, mapping: str = "raw", drive_node_id: int = 2) -> int:
    """Write the merged DBC to ``out`` (a temporary file renamed over it, so a failure
    leaves no half-written file; only a regular file is ever replaced), the drive's PDOs
    as the shipped ``mapping`` configures them.  Returns the number of messages written."""
    from hdhil.dbc import dbc_path

    if out.exists() and not out.is_file():
        raise UserError(f"{out}: exists and is not a regular file")
    check_output(out)  # a regular file or a new one, in an existing directory
    check_not_inputs([(out, "")], [(dbc_path(bus), "database") for bus in ("control", "truth")])
    text = merged_dbc_text(mapping, drive_node_id)
    with atomic_path(out) as tmp:
        try:
            tmp.write_text(text, encoding="cp1252", errors="strict", newline="\r\n")
        except (OSError, UnicodeEncodeError) as exc:
            reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
            raise UserError(f"cannot write {out}: {reason}") from None
    return text.count("\nBO_ ")


def bus_outputs(out: Path, buses: list[str]) -> dict[str, Path]:
    """Where each bus's database goes: ``out`` itself for one bus, else ``out``'s stem
    with the bus's name (``rig.dbc`` -> ``rig-can0.dbc``, ``rig-can1.dbc``)."""
    if len(buses) == 1:
        return {buses[0]: out}
    return {bus: out.with_name(f"{out.stem}-{bus}{out.suffix or '.dbc'}") for bus in buses}


def export_scenario(out: Path, scenario: str, mapping: str = "raw") -> dict[str, tuple[Path, int]]:
    """Write the database of each bus of ``scenario``'s rig (:mod:`hdhil.canopen.rigdb`,
    from the object dictionaries and node-IDs): one DBC per bus (:func:`bus_outputs`),
    all written or none. Returns, per bus, the file and its number of messages."""
    import cantools

    from hdhil.analysis.rigplan import scenario_databases
    from hdhil.core.files import AtomicOutput, commit_outputs, discard_outputs
    from hdhil.rig.scenario import load_scenario

    databases = scenario_databases(load_scenario(scenario), mapping)
    targets = bus_outputs(out, list(databases))
    texts = {}
    for bus, db in databases.items():
        text = db.as_dbc_string()
        cantools.database.load_string(text, database_format="dbc", strict=True)
        texts[bus] = text
    outputs = []
    try:
        for bus, path in targets.items():
            if path.exists() and not path.is_file():
                raise UserError(f"{path}: exists and is not a regular file")
            check_output(path)
            o = AtomicOutput(path, "", open_file=False, deferred=True)
            outputs.append(o)
            with o:
                assert o.path is not None
                try:
                    o.path.write_text(texts[bus], encoding="cp1252", errors="strict",
                                      newline="\r\n")  # fmt: skip
                except (OSError, UnicodeEncodeError) as exc:
                    reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
                    raise UserError(f"cannot write {path}: {reason}") from None
        commit_outputs(outputs)
    except BaseException:
        discard_outputs(outputs)
        raise
    return {bus: (targets[bus], texts[bus].count("\nBO_ ")) for bus in databases}


def run_export(args: argparse.Namespace) -> int:
    node = 2 if args.drive_node_id is None else args.drive_node_id
    if node == 1:
        raise UserError("drive node-ID 1 is the controller's: give the drive another (2..127)")
    if args.scenario is not None:
        if args.drive_node_id is not None:
            raise UserError("--scenario names its drives' node-IDs: leave out --drive-node-id")
        written = export_scenario(Path(args.out), args.scenario, args.mapping)
        for bus, (path, n) in written.items():
            print(f"hdhil dbc export: bus {bus}: {n} messages (its frames and its joints' "
                  f"ground truth) in {path}")  # fmt: skip
        return 0
    n = export(Path(args.out), args.mapping, node)
    what = "" if args.mapping == "raw" else f", the drive's PDOs in the {args.mapping} mapping"
    if node != 2:
        what += f", the drive at node-ID {node}"
    print(f"hdhil dbc export: {n} messages (control bus and ground truth{what}) in {args.out}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "dbc",
        help="CAN databases: export the control bus and ground truth as one DBC",
        description="Work with the CAN databases of the drive link.",
    )
    actions = p.add_subparsers(dest="dbc_action", metavar="ACTION", required=True)
    e = actions.add_parser(
        "export",
        help="write one DBC with every frame of a trace (control bus and ground truth)",
        description="Write control.dbc and truth.dbc merged into one DBC, for tools that "
        "take one database per trace (cantools decode/plot, CANalyzer, asammdf).",
    )
    e.add_argument("out", metavar="OUT.dbc", help="the DBC file to write")
    from hdhil.dbc import MAPPINGS

    e.add_argument(
        "--mapping",
        choices=list(MAPPINGS),
        default="raw",
        metavar="NAME",
        help=f"the drive's PDO messages as this shipped mapping configures them "
        f"({', '.join(MAPPINGS)}; default raw, control.dbc as it is)",
    )
    e.add_argument(
        "--scenario",
        metavar="NAME",
        help="the databases of this scenario's rig, generated from the drives' object "
        "dictionaries and node-IDs: one DBC per bus (OUT's stem with the bus's name when "
        "there are several)",
    )
    from hdhil.commands.options import add_drive_node_id_argument

    add_drive_node_id_argument(e)
    e.set_defaults(func=run_export)
