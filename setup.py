# Why this file exists: setuptools takes cffi extension modules (and plain C
# shared libraries) from setup() keywords, not from pyproject.toml, and the
# package mapping is computed. Everything else is in pyproject.toml.
#
# The container's sources stay in the repository's container/ folder; they
# install as cloneguard.container, under the project's own namespace
# (`cloneguard`, shared with the test rig's cloneguard.harness/.faults/.bench,
# rig/setup.py), never as a bare top-level `container`.
import runpy
import sys
from pathlib import Path

import pybind11
from setuptools import Extension, find_packages, setup
from setuptools.command.build_ext import build_ext

# The project's C warning flags: one list for every build (scripts/cflags.py).
_CFLAGS = runpy.run_path(str(Path(__file__).resolve().parent / "scripts" / "cflags.py"))
WARNINGS, CXX_WARNINGS = _CFLAGS["WARNINGS"], _CFLAGS["CXX_WARNINGS"]

# Isolated mode's C (the clone core, the allocator guard) rests on glibc and
# x86_64 layouts: where it does not build, the rest of the container (thread
# mode) still installs, and --isolated refuses with the reason.
ISOLATED_ONLY = {
    "cloneguard.container.isolated._clonecore",
    "cloneguard.container.isolated._allocguard",
    "cloneguard.container.isolated._pylocks",
    "cloneguard.container.isolated._pybind11_registry",
    "cloneguard.container.isolated._dds_defaults",
}


class BuildExt(build_ext):
    def build_extension(self, ext):
        try:
            super().build_extension(ext)
        except Exception as exc:
            if ext.name not in ISOLATED_ONLY:
                raise
            self.warn(f"{ext.name} was not built ({exc}): --isolated will be unavailable")


PACKAGE = "cloneguard.container"

setup(
    packages=[PACKAGE] + [f"{PACKAGE}.{sub}" for sub in find_packages("container")],
    package_dir={PACKAGE: "container"},
    cmdclass={"build_ext": BuildExt},
    cffi_modules=[
        "container/_build_robust.py:ffibuilder",
        "container/isolated/_build_core.py:ffibuilder",
        "container/_build_rclglue.py:ffibuilder",
    ],
    ext_modules=[
        # Not a Python module: the allocator guard, a plain shared library an
        # isolated container preloads (container/isolated/allocguard/). Built
        # here so that it lands beside the package like the cffi modules.
        Extension(
            "cloneguard.container.isolated._allocguard",
            sources=[
                "container/isolated/allocguard/allocguard.c",
                "container/isolated/allocguard/pyalloc.c",
                "container/isolated/allocguard/heapkeys.c",
                "container/isolated/allocguard/stops.c",
                "container/isolated/allocguard/bigblocks.c",
            ],
            depends=["container/isolated/allocguard/allocguard.h", "container/isolated/allocguard/guard_internal.h"],
            extra_compile_args=["-std=gnu11", "-O2", *WARNINGS, "-fvisibility=hidden", "-fno-builtin"],
            libraries=["dl", "pthread"],
        ),
        # Python's lock types for an isolated container (pylocks.c).
        Extension(
            "cloneguard.container.isolated._pylocks",
            sources=["container/isolated/pylocks.c"],
            depends=["container/isolated/allocguard/allocguard.h"],
            extra_compile_args=["-std=gnu11", *WARNINGS],
        ),
        # Not a Python module: the default QoS of the DDS participants made
        # from then on (dds_defaults.cpp), against the venv's Fast DDS.
        Extension(
            "cloneguard.container.isolated._dds_defaults",
            sources=["container/isolated/dds_defaults.cpp"],
            include_dirs=[str(Path(sys.prefix) / "include")],
            library_dirs=[str(Path(sys.prefix) / "lib")],
            libraries=["fastrtps"],
            language="c++",
            extra_compile_args=["-std=c++17", "-O2", *CXX_WARNINGS, "-fvisibility=hidden"],
        ),
        # pybind11's instance registry kept ahead of the node processes
        # (pybind11_registry.cpp): built against the pybind11 ABI rclpy uses.
        Extension(
            "cloneguard.container.isolated._pybind11_registry",
            sources=["container/isolated/pybind11_registry.cpp"],
            include_dirs=[pybind11.get_include()],
            language="c++",
            extra_compile_args=["-std=c++17", "-O2", *CXX_WARNINGS, "-fvisibility=hidden"],
        ),
    ],
)
