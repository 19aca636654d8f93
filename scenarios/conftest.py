"""Shared glue for scenarios: rigs.

Trial counts, seeds and shards (``--deep``, ``--trials N``, ``--seed S``,
``--shard K/N``) and the ``trial_plan``/``record_trial``/``run_trials``
fixtures come from the harness's pytest plugin (harness/plan.py).
"""

import pytest

from cloneguard.harness.rig import Rig


@pytest.fixture
def rig_factory(container_factory):
    def make(profile: str, **kwargs) -> Rig:
        return Rig(container_factory, profile, **kwargs)

    return make
