"""Configuring a node at boot from a DCF (CiA 306 device configuration file), as CANopen
masters such as lely's and ros2_canopen's do.

A DCF is the node's EDS with a ``ParameterValue`` for each object the master sets; the
format is canopen's (``canopen.import_od`` reads it). :func:`configuration_writes` turns
it into the SDO downloads, ordered as CiA 301 requires for PDOs (the PDO made not valid
first, mapping sub-index 0 to 0, the entries, sub-index 0 to n, the final COB-ID last);
:class:`DcfConfigurator` sends them one at a time through the non-blocking
:class:`hdhil.canopen.sdo.SdoClient`, so a node in the lockstep loop never blocks.
"""

from __future__ import annotations

from pathlib import Path

import canopen
from canopen.objectdictionary import ODVariable

from hdhil.canopen.od import is_comm_index, is_mapping_index
from hdhil.canopen.pdo import PDO_NOT_VALID
from hdhil.canopen.sdo import SdoClient, SdoResult, abort_text

__all__ = ["DcfConfigurator", "configuration_writes"]

Write = tuple[int, int, bytes]


def _configured(od: canopen.ObjectDictionary) -> dict[tuple[int, int], ODVariable]:
    out = {}
    for index in od:
        obj = od[index]
        variables = [obj] if isinstance(obj, ODVariable) else list(obj.values())
        for var in variables:
            if getattr(var, "value", None) is not None:
                out[(var.index, var.subindex)] = var
    return out


def configuration_writes(path: str | Path, node_id: int) -> list[Write]:
    """The SDO downloads that configure node ``node_id`` as the DCF at ``path`` says.

    Raises ``ValueError`` for a file canopen cannot read, a value that does not encode
    in its object's type, or one longer than 4 bytes (expedited transfers only).
    """
    try:
        od = canopen.import_od(str(path), node_id)
    except Exception as exc:
        raise ValueError(f"{path}: not a readable DCF/EDS ({exc})") from None
    configured = _configured(od)
    # Each COB-ID of the pre-defined connection set at the node's node-ID, whatever
    # node-ID the file was written for (hdhil.canopen.rigdb.drive_pdo_layouts).
    from hdhil.canopen.rigdb import RigDrive, drive_pdo_layouts
    from hdhil.core.errors import UserError

    try:
        at_node = {
            layout.comm_index: layout.cob_id
            for layout in drive_pdo_layouts(RigDrive("", node_id, dcf=path)).values()
        }
    except UserError as exc:
        raise ValueError(str(exc)) from None

    def data(var: ODVariable, value: object) -> bytes:
        try:
            raw = var.encode_raw(value)
        except Exception as exc:
            raise ValueError(
                f"{path}: 0x{var.index:04X}:{var.subindex:02X} = {value!r}: {exc}"
            ) from None
        if not 1 <= len(raw) <= 4:
            raise ValueError(
                f"{path}: 0x{var.index:04X}:{var.subindex:02X} needs {len(raw)} bytes; "
                "only values of up to 4 bytes are configured (expedited SDO)"
            )
        return raw

    writes: list[Write] = []
    pdo_comms = sorted(
        {i for i, _ in configured if is_comm_index(i)}
        | {i - 0x200 for i, _ in configured if is_mapping_index(i)}
    )
    for (index, sub), var in sorted(configured.items()):
        if not (is_comm_index(index) or is_mapping_index(index)):
            writes.append((index, sub, data(var, var.value)))
    for comm in pdo_comms:
        mapping = comm + 0x200
        cob_var = od[comm][1]
        cob = cob_var.value if cob_var.value is not None else cob_var.default
        cob = (cob & ~0x7FF) | at_node.get(comm, cob & 0x7FF)
        writes.append((comm, 1, data(cob_var, cob | PDO_NOT_VALID)))
        for (index, sub), var in sorted(configured.items()):
            if index == comm and sub != 1:
                writes.append((index, sub, data(var, var.value)))
        entries = [(s, v) for (i, s), v in sorted(configured.items()) if i == mapping]
        if entries:
            count_var = od[mapping][0]
            count = count_var.value if count_var.value is not None else count_var.default
            writes.append((mapping, 0, data(count_var, 0)))
            for sub, var in entries:
                if sub != 0:
                    writes.append((mapping, sub, data(var, var.value)))
            writes.append((mapping, 0, data(count_var, count)))
        writes.append((comm, 1, data(cob_var, cob)))
    return writes


class DcfConfigurator:
    """Sends the writes one at a time; :meth:`on_result` moves on.

    ``error`` is the one-line reason when the node refused a write (its abort code and
    CiA 301 text); ``done`` once every write was accepted.
    """

    def __init__(self, client: SdoClient, writes: list[Write]) -> None:
        self.client = client
        self.writes = list(writes)
        self.position = 0
        self.error: str | None = None
        self.started = False

    @property
    def done(self) -> bool:
        return self.started and self.error is None and self.position >= len(self.writes)

    @property
    def busy(self) -> bool:
        return self.started and self.error is None and self.position < len(self.writes)

    def start(self) -> None:
        self.started = True
        self._send()

    def on_result(self, result: SdoResult) -> None:
        index, sub, data = self.writes[self.position]
        if not result.ok:
            code = result.abort or 0
            self.error = (
                f"node {self.client.server_node_id} refused 0x{index:04X}:{sub:02X} = "
                f"0x{int.from_bytes(data, 'little'):X} from the DCF: abort 0x{code:08X} "
                f"({abort_text(code)})"
            )
            return
        self.position += 1
        self._send()

    def _send(self) -> None:
        if self.position < len(self.writes):
            index, sub, data = self.writes[self.position]
            self.client.download(index, sub, data)
