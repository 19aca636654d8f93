from pathlib import Path

import pytest

from cloneguard.harness.process import use_loopback_ros

FIXTURES = Path(__file__).parent / "fixtures"


def pytest_configure(config):
    # These tests also make ROS nodes in the test process itself
    # (ros_support.py), outside the harness's fixtures: the whole run follows
    # the containers' rules (Fast DDS, UDP on loopback only).
    use_loopback_ros()


# Tests that start a container process (through the harness's fixtures) are
# marked "container"; the rest are quick: `./scripts/test.sh -m "not
# container"` is the edit loop (about a minute), the whole suite ~10.
CONTAINER_FIXTURES = {"container_factory", "container", "client"}


def pytest_collection_modifyitems(config, items):
    for item in items:
        if CONTAINER_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.container)


@pytest.fixture(autouse=True)
def _leftovers_checked(_leftovers):
    """The harness's leftovers check after every test here, whether it
    started a container or a process of its own."""
    yield _leftovers


MISFITS = {
    "misfits::Raises": "misfit_components:RaisesInConstructor",
    "misfits::NotANode": "misfit_components:NotANode",
    "misfits::IgnoresOptions": "misfit_components:IgnoresOptions",
    "misfits::DeclaresInteger": "misfit_components:DeclaresInteger",
    "misfits::DebugLogger": "misfit_components:DebugLogger",
    "misfits::ExitsInConstructor": "misfit_components:ExitsInConstructor",
    "misfits::Missing": "misfit_components_that_do_not_exist:Nothing",
}


def _throwaway_distribution(site: Path, name: str, module: str, groups: dict[str, dict[str, str]]) -> Path:
    """Install module ``module`` of tests/fixtures into ``site`` as an
    installed (dist-info) distribution ``name`` whose entry points are
    ``groups`` (group -> {entry point name: target}); put ``site`` on a
    container's PYTHONPATH to make them loadable."""
    dist = site / f"{name.replace('-', '_')}-0.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 0.0\n")
    (dist / "entry_points.txt").write_text(
        "".join(
            f"[{group}]\n" + "".join(f"{k} = {v}\n" for k, v in entries.items()) for group, entries in groups.items()
        )
    )
    (site / f"{module}.py").write_text((FIXTURES / f"{module}.py").read_text())
    return site


@pytest.fixture(scope="session")
def misfit_site(tmp_path_factory) -> Path:
    """Bad components ("misfit-components"), and one registered only in
    rclpy's composition proposal's group."""
    return _throwaway_distribution(
        tmp_path_factory.mktemp("misfit_site"),
        "misfit-components",
        "misfit_components",
        {
            "cloneguard.components": MISFITS,
            "rclpy_components": {"misfits::RclpyStyle": "misfit_components:RclpyStyle"},
        },
    )


@pytest.fixture(scope="session")
def node_kinds_site(tmp_path_factory) -> Path:
    """A component per kind of rclpy entity ("node-kinds": fixtures/node_kinds.py)."""
    from fixtures.node_kinds import KINDS

    return _throwaway_distribution(
        tmp_path_factory.mktemp("node_kinds_site"), "node-kinds", "node_kinds", {"cloneguard.components": KINDS}
    )


@pytest.fixture
def misfit_env(misfit_site):
    return {"PYTHONPATH": str(misfit_site)}


@pytest.fixture
def limited_system(system_factory):
    """system_factory(nodes, container_args, limit): the container in a
    memory cgroup of the harness's own with that limit; the test is skipped,
    saying why, where no memory cgroup can be made."""
    from cloneguard.harness.memory_cgroup import MemoryCgroupUnavailable

    def make(nodes, container_args, limit: int):
        try:
            return system_factory(nodes, container_args, memory_limit=limit)
        except MemoryCgroupUnavailable as why:
            pytest.skip(f"no memory cgroup can be made here: {why}")

    return make
