"""The faults cloneguard's harness injects: fault components, outside
signals, the malloc hammer, and one trial of each (trials.py).

Part of the test rig (rig/pyproject.toml), never of the product: a
container installed without the rig cannot load a fault component.
"""

#: LoadNode package_name of the rig's components (faults::*, bench::*):
#: the test rig's distribution, cloneguard-testrig.
PACKAGE = "cloneguard_testrig"
