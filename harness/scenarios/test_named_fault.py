"""The scenario ``python -m cloneguard.harness reproduce NAME`` runs: the
trials of the fault a package of yours declares as NAME (named_faults.py),
given to pytest as ``--named-fault NAME``. Not a package: pytest imports it
by path (``--import-mode=importlib``), and it imports only the harness."""

from cloneguard.harness import named_faults


def test_named_fault(request, system_factory, system_trials):
    name = request.config.getoption("--named-fault")
    if name is None:
        raise AssertionError("run this with --named-fault NAME (python -m cloneguard.harness reproduce NAME)")
    named_faults.load(name).run(system_factory, system_trials)
