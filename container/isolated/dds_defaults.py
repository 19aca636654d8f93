"""How often the DDS participants of node processes announce themselves
(dds_defaults.cpp: why only the container's own participant must be found
fast, and what this rests on), and Fast DDS's intraprocess delivery off.

``announce_nodes_every(seconds)`` and ``intraprocess_off()`` are called
once, in the container, after its own participant exists and before any
node process's is made."""

from __future__ import annotations

import ctypes
import functools
import sysconfig
from pathlib import Path

LIBRARY = Path(__file__).resolve().parent / f"_dds_defaults{sysconfig.get_config_var('EXT_SUFFIX')}"
#: a participant's lease, in announcement periods (Fast DDS's own default:
#: a 20 s lease, an announcement every 3 s)
LEASE_PERIODS = 7


class DdsDefaultsUnavailable(RuntimeError):
    pass


@functools.cache
def _lib() -> ctypes.CDLL:
    try:
        lib = ctypes.CDLL(str(LIBRARY))
    except OSError as exc:
        raise DdsDefaultsUnavailable(f"its library was not built or does not load ({exc})") from None
    for name in ("cg_dds_announcement", "cg_dds_set_announcement", "cg_dds_intraprocess_off"):
        getattr(lib, name).restype = ctypes.c_int
    lib.cg_dds_intraprocess_off.argtypes = [ctypes.POINTER(ctypes.c_int)]
    lib.cg_dds_announcement.argtypes = [ctypes.POINTER(ctypes.c_int64), ctypes.POINTER(ctypes.c_int64)]
    lib.cg_dds_set_announcement.argtypes = [ctypes.c_int64, ctypes.c_int64]
    return lib


def announcement() -> tuple[float, float]:
    """(announcement period, lease) in s of the participants made next."""
    period, lease = ctypes.c_int64(), ctypes.c_int64()
    if _lib().cg_dds_announcement(ctypes.byref(period), ctypes.byref(lease)) != 0:
        raise DdsDefaultsUnavailable("Fast DDS has no participant factory")
    return period.value / 1e9, lease.value / 1e9


def announce_nodes_every(seconds: float) -> tuple[float, float]:
    """Participants made from now on announce every ``seconds`` (their
    lease LEASE_PERIODS times that, or the profile's if longer); the
    period before and after."""
    before, lease = announcement()
    period_ns = round(seconds * 1e9)
    lease_ns = max(round(lease * 1e9), LEASE_PERIODS * period_ns)
    if _lib().cg_dds_set_announcement(period_ns, lease_ns) != 0:
        raise DdsDefaultsUnavailable(f"Fast DDS refused an announcement period of {seconds:g} s")
    return before, announcement()[0]


#: Fast DDS's IntraprocessDeliveryType, by value
INTRAPROCESS = ("OFF", "USER_DATA_ONLY", "FULL")


def intraprocess_off() -> str:
    """Fast DDS's intraprocess delivery off for every match made from now
    on (docs/fastdds.md says why an isolated container needs it); what the
    profile had (``INTRAPROCESS``)."""
    was = ctypes.c_int()
    _lib().cg_dds_intraprocess_off(ctypes.byref(was))
    return INTRAPROCESS[was.value] if 0 <= was.value < len(INTRAPROCESS) else str(was.value)
