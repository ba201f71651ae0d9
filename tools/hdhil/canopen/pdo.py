"""PDO mapping checks (CiA 301 §7.4.7.1, §7.5.2.35-38) on the object dictionary.

The mapping objects (RPDO 0x1600-0x17FF, TPDO 0x1A00-0x1BFF) are checked when written,
over SDO or by the application: an entry must name an object that exists (0x06020000),
is PDO-mappable (0x06040041) and whose length it states (0x06040043); a dummy entry
(data types 0x0001-0x0007) must state the type's size; sub-index 0 may not enable more
entries than exist or more than 64 bits (0x06040042).
"""

from __future__ import annotations

from collections.abc import Callable

from canopen.objectdictionary import ObjectDictionary

from hdhil.canopen.od import variable
from hdhil.canopen.sdo import (
    ABORT_INCOMPATIBLE,
    ABORT_NO_OBJECT,
    ABORT_NOT_MAPPABLE,
    ABORT_PDO_LENGTH,
)

__all__ = ["DUMMY_BITS", "MAX_PDO_BITS", "check_mapping_count", "check_mapping_entry"]

#: Bit size of the dummy-mapping data types 0x0001..0x0007 (CiA 301 §7.4.7.1).
DUMMY_BITS = {0x1: 1, 0x2: 8, 0x3: 16, 0x4: 32, 0x5: 8, 0x6: 16, 0x7: 32}

#: A classical CAN PDO carries at most 8 bytes.
MAX_PDO_BITS = 64


def check_mapping_entry(od: ObjectDictionary, value: int) -> int | None:
    """Abort code for a mapping entry ``index << 16 | sub << 8 | bits``, None if valid."""
    if value == 0:
        return None
    index, sub, bits = value >> 16, (value >> 8) & 0xFF, value & 0xFF
    if index in DUMMY_BITS:
        return None if sub == 0 and bits == DUMMY_BITS[index] else ABORT_INCOMPATIBLE
    var = variable(od, index, sub)
    if var is None:
        return ABORT_NO_OBJECT
    if not var.pdo_mappable:
        return ABORT_NOT_MAPPABLE
    if bits != len(var):
        return ABORT_INCOMPATIBLE
    return None


def check_mapping_count(
    od: ObjectDictionary, read: Callable[[int, int], int], index: int, count: int
) -> int | None:
    """Abort code for writing ``count`` to sub-index 0 of mapping object ``index``.

    ``read(index, sub)`` returns the entries as stored now.
    """
    obj = od.get(index)
    entries = [s for s in getattr(obj, "subindices", {}) if s > 0]
    if count > len(entries):
        return ABORT_PDO_LENGTH
    total = 0
    for sub in range(1, count + 1):
        total += read(index, sub) & 0xFF
    return ABORT_PDO_LENGTH if total > MAX_PDO_BITS else None
