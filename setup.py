# The only reason this file exists: setuptools takes cffi extension modules
# (and plain C shared libraries) from setup() keywords, not from
# pyproject.toml. Everything else is there.
from setuptools import Extension, setup

setup(
    cffi_modules=[
        "container/isolated/_build_core.py:ffibuilder",
        "faults/_build_hammer.py:ffibuilder",
        "container/intra/_build_rclglue.py:ffibuilder",
    ],
    ext_modules=[
        # Not a Python module: the allocator guard, a plain shared library an
        # isolated container preloads (container/isolated/allocguard.c). Built
        # here so that it lands beside the package like the cffi modules.
        Extension(
            "container.isolated._allocguard",
            sources=["container/isolated/allocguard.c"],
            depends=["container/isolated/allocguard.h"],
            extra_compile_args=["-std=gnu11", "-O2", "-Wall", "-fvisibility=hidden", "-fno-builtin"],
            libraries=["dl", "pthread"],
        ),
    ],
)
