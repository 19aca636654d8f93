"""cffi (API mode) builder for faults._nativelock (nativelock.c: native locks
every node process of an isolated container shares, and dying holding
them)."""

import runpy
from pathlib import Path

_shared = runpy.run_path(str(Path(__file__).with_name("_cffi_fault.py")))
fault_builder, header_cdef = _shared["fault_builder"], _shared["header_cdef"]

ffibuilder = fault_builder("nativelock", header_cdef("nativelock"), libraries=["pthread"])
