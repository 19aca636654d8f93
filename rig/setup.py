# The test rig's packages live in the repository's top-level folders
# (harness/, faults/, bench/), one level up from this file, and install under
# the project's namespace beside the product's cloneguard.container:
# cloneguard.harness, cloneguard.faults, cloneguard.bench. setuptools takes
# the computed package mapping and cffi_modules from setup() keywords;
# everything else is in rig/pyproject.toml.
from setuptools import find_packages, setup

FOLDERS = ("harness", "faults", "bench")

setup(
    packages=[
        f"cloneguard.{top}{'.' + sub if sub else ''}" for top in FOLDERS for sub in ["", *find_packages(f"../{top}")]
    ],
    package_dir={f"cloneguard.{top}": f"../{top}" for top in FOLDERS},
    # The scenario `reproduce NAME` runs (harness/named_faults.py): a test
    # file pytest imports by path, not a module of the package.
    package_data={"cloneguard.harness": ["scenarios/test_named_fault.py"]},
    cffi_modules=[
        "../faults/_build_hammer.py:ffibuilder",
        "../faults/_build_gilfault.py:ffibuilder",
        "../faults/_build_interpfault.py:ffibuilder",
        "../faults/_build_nativelock.py:ffibuilder",
    ],
)
