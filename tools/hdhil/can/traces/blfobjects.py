"""Classical CAN frames into python-can's BLF writer in bulk, byte for byte as it writes them.

The trace writer's process (:mod:`hdhil.can.traces.writer`) spends most of its time in
python-can's :class:`can.BLFWriter` turning each :class:`can.Message` into one BLF object
(``on_message_received`` then ``_add_object``: a dozen attribute reads, three ``struct``
calls and four list appends per frame).  On a machine whose cores the run shares, that
time is taken from the run itself.  :func:`bulk_blf_writer` packs each classical data or
remote frame's whole object (object header, timestamp header, CAN_MESSAGE body) in one
``struct`` call and hands a batch's objects to the writer's buffer in one piece, which
the writer then cuts into containers and compresses exactly as it would have: the file
is the same, byte for byte (tested against python-can's own path).  Error frames go
through the writer's own method.

It relies on the writer's buffer attributes, so it is used only for the exact
:class:`can.io.blf.BLFWriter` class whose module and instance have every name it uses,
and with object sizes that need no padding; anything else gets ``None`` and the caller
keeps python-can's per-message path.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable
from typing import Any

import can

#: A record as the trace writer's pipe carries it: timestamp, identifier, extended,
#: remote, error frame, received, DLC, channel number, payload.
Record = tuple[float, int, bool, bool, bool, bool, int, int, bytes]

_MODULE_NAMES = ("BLFWriter", "OBJ_HEADER_BASE_STRUCT", "OBJ_HEADER_V1_STRUCT", "CAN_MSG_STRUCT",
                 "CAN_MESSAGE", "CAN_MSG_EXT", "REMOTE_FLAG", "DIR", "TIME_ONE_NANS")  # fmt: skip
_WRITER_NAMES = ("_buffer", "_buffer_size", "object_count", "start_timestamp",
                 "stop_timestamp", "max_container_size", "_flush")  # fmt: skip


def bulk_blf_writer(
    writer: Any, offset: float, one_by_one: Callable[[Record], None]
) -> Callable[[Iterable[Record]], int] | None:
    """A function writing records to python-can's BLF ``writer`` as its
    ``on_message_received`` would (each timestamp plus ``offset``), returning how many; error
    frames go to ``one_by_one``.  None when ``writer`` is not a writer this can serve."""
    blf = getattr(getattr(can, "io", None), "blf", None)
    if blf is None or not all(hasattr(blf, name) for name in _MODULE_NAMES):
        return None
    if type(writer) is not blf.BLFWriter or not all(hasattr(writer, n) for n in _WRITER_NAMES):
        return None
    if not isinstance(writer._buffer, list):
        return None
    base, v1, body = blf.OBJ_HEADER_BASE_STRUCT, blf.OBJ_HEADER_V1_STRUCT, blf.CAN_MSG_STRUCT
    header_size = base.size + v1.size
    object_size = header_size + body.size
    if body.size % 4:  # the writer would pad each object
        return None
    try:
        whole = struct.Struct("<" + "".join(s.format.lstrip("<") for s in (base, v1, body)))
    except (struct.error, AttributeError, TypeError):
        return None
    if whole.size != object_size:
        return None
    pack = whole.pack
    kind, time_flags = blf.CAN_MESSAGE, blf.TIME_ONE_NANS
    extended_flag, remote_flag, tx_flag = blf.CAN_MSG_EXT, blf.REMOTE_FLAG, blf.DIR

    def commit(objects: list[bytes], last: float) -> None:
        """Hand packed objects to the writer's buffer as ``_add_object`` leaves it after
        them: containers are cut from the same byte stream at the same sizes."""
        chunk = b"".join(objects)
        writer._buffer.append(chunk)
        writer._buffer_size += len(chunk)
        writer.object_count += len(objects)
        writer.stop_timestamp = last
        while writer._buffer_size >= writer.max_container_size:
            writer._flush()

    def write(records: Iterable[Record]) -> int:
        objects: list[bytes] = []
        append = objects.append
        start = writer.start_timestamp
        last = 0.0
        n = 0
        for record in records:
            n += 1
            ts, can_id, extended, remote, error, rx, dlc, channel, data = record
            if error:  # another kind of BLF object: the writer's own method, in order
                if objects:
                    commit(objects, last)
                    objects.clear()
                one_by_one(record)
                start = writer.start_timestamp
                continue
            t = ts + offset
            if start is None:  # as _add_object: the first object's time, to the ms
                start = writer.start_timestamp = int(t * 1000) / 1000
            ns = int((t - start) * 1e9)
            append(pack(b"LOBJ", header_size, 1, object_size, kind,
                        time_flags, 0, 0, ns if ns > 0 else 0,
                        channel + 1, (remote_flag if remote else 0) | (0 if rx else tx_flag),
                        dlc, can_id | extended_flag if extended else can_id,
                        b"" if remote else data))  # fmt: skip
            last = t
        if objects:
            commit(objects, last)
        return n

    return write
