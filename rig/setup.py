# The test rig's packages live in the repository's top-level folders
# (harness/, faults/, bench/), one level up from this file; setuptools takes
# package_dir and cffi_modules from setup() keywords. Everything else is in
# rig/pyproject.toml.
from setuptools import find_packages, setup

setup(
    packages=find_packages(where="..", include=["harness*", "faults*", "bench*"]),
    package_dir={"": ".."},
    cffi_modules=["../faults/_build_hammer.py:ffibuilder", "../faults/_build_gilfault.py:ffibuilder"],
)
