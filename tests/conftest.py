from pathlib import Path

import pytest

FIXTURES = Path(__file__).parent / "fixtures"

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
    (dist / "entry_points.txt").write_text("[cloneguard.components]\n" + lines
                                           + "[rclpy_components]\nmisfits::RclpyStyle = misfit_components:RclpyStyle\n")
    (site / "misfit_components.py").write_text((FIXTURES / "misfit_components.py").read_text())
    return site


@pytest.fixture
def misfit_env(misfit_site):
    return {"PYTHONPATH": str(misfit_site)}
