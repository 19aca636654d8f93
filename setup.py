# The only reason this file exists: setuptools takes cffi extension modules
# from setup() keywords, not from pyproject.toml. Everything else is there.
from setuptools import setup

setup(
    cffi_modules=[
        "container/isolated/_build_core.py:ffibuilder",
        "faults/_build_hammer.py:ffibuilder",
        "container/intra/_build_rclglue.py:ffibuilder",
    ]
)
