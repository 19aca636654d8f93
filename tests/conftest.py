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


@pytest.fixture(scope="session")
def misfit_site(tmp_path_factory) -> Path:
    """A directory holding an installed (dist-info) distribution of bad
    components; put it on a container's PYTHONPATH to make them loadable."""
    site = tmp_path_factory.mktemp("misfit_site")
    dist = site / "misfit_components-0.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: misfit-components\nVersion: 0.0\n")
    lines = "".join(f"{name} = {target}\n" for name, target in MISFITS.items())
    # One more, registered only in rclpy's composition proposal's group.
    (dist / "entry_points.txt").write_text(
        "[cloneguard.components]\n" + lines + "[rclpy_components]\nmisfits::RclpyStyle = misfit_components:RclpyStyle\n"
    )
    (site / "misfit_components.py").write_text((FIXTURES / "misfit_components.py").read_text())
    return site


@pytest.fixture
def misfit_env(misfit_site):
    return {"PYTHONPATH": str(misfit_site)}
