"""Fast DDS shared-memory segments: none under the harness profile, none
after a graceful stop, and after a SIGKILL only the orphans are removed."""
import signal

from faults.outside import sigkill_container
from harness import procfs, shm
from harness.process import SHM_PROFILE
from harness.rig import Outcome


def test_no_shm_profile_creates_no_segment(rig_factory, resilience, record_trial):
    resilience.describe(fault="none", profile="per-node", mitigations={"fastdds_profile": "no-shm"},
                        claim="under fixtures/fastdds_no_shm.xml no /dev/shm/fastrtps_* file is created")
    before = shm.segments()
    rig = rig_factory("per-node")
    rig.client.load_ok("cloneguard", "cloneguard::Talker")
    created = shm.segments() - before
    record_trial(0, 0, Outcome("survived" if not created else "failed", details={"created": sorted(created)}))
    resilience.expect_rate("survived", at_least=1.0)


def test_graceful_stop_with_shm_leaks_nothing(rig_factory, resilience, record_trial):
    resilience.describe(fault="sigterm-container", profile="per-node", mitigations={"fastdds_profile": "shm"},
                        claim="with the SHM transport on, a graceful stop (SIGTERM) removes every "
                              "segment the container and its children made")
    before = shm.segments()
    rig = rig_factory("per-node", fastdds_profile=SHM_PROFILE)
    rig.client.load_ok("cloneguard", "cloneguard::Talker")
    created = shm.segments() - before
    rig.client.close()
    rig.proc.signal(signal.SIGTERM)
    code = rig.proc.wait(timeout=10)
    left = shm.segments() & created
    ok = created and not left and code == 0
    record_trial(0, 0, Outcome("survived" if ok else "failed",
                               details={"created": len(created), "left": sorted(left), "exit_code": code}))
    resilience.expect_rate("survived", at_least=1.0)


def test_sigkilled_container_leaves_orphans_that_are_found_and_removed(rig_factory, resilience, record_trial):
    resilience.describe(fault="sigkill-container", profile="per-node", mitigations={"fastdds_profile": "shm"},
                        claim="a SIGKILLed container leaves orphaned SHM segments; the harness finds "
                              "them the way Fast DDS does (their lock files can be locked) and removes "
                              "only those, leaving the segments of a live container alone")
    before = shm.segments()
    bystander = rig_factory("per-node", fastdds_profile=SHM_PROFILE)   # stays alive throughout
    victim = rig_factory("per-node", fastdds_profile=SHM_PROFILE)
    victim.client.load_ok("cloneguard", "cloneguard::Talker")
    victim.client.close()
    ours = victim.proc.record_shm()          # what it maps: the only candidates
    sigkill_container(victim.proc)
    victim.proc.wait(timeout=10)
    # Its node processes die of PR_SET_PDEATHSIG right after it.
    procfs.wait_group_empty(victim.proc.pgid, timeout=10)
    candidates = shm.segments() - before
    in_use = {f for seg in shm.classify(candidates) if not seg.orphan for f in seg.files}
    removed = shm.remove_orphans_of(candidates, ours)
    left_orphans = [seg.name for seg in shm.classify(shm.segments() - before)
                    if seg.orphan and seg.name in ours]
    ok = (removed and in_use <= shm.segments() and not left_orphans
          and bystander.goes_on() is None)
    record_trial(0, 0, Outcome("survived" if ok else "failed", details={
        "orphans_removed": [s.name for s in removed], "in_use_kept": len(in_use), "orphans_left": left_orphans}))
    resilience.note(f"{len(removed)} orphaned segment(s) removed; {len(in_use)} files in use by the "
                    "live container kept")
    resilience.expect_rate("survived", at_least=1.0)
