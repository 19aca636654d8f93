"""Fast DDS shared-memory segments: none under the harness profile, none
after a graceful stop, and after a SIGKILL only the orphans are removed."""

import signal

from cloneguard.faults.outside import sigkill_container
from cloneguard.harness import procfs, rest, shm
from cloneguard.harness.process import SHM_PROFILE
from cloneguard.harness.rig import Outcome, Rig, TrialOutcome


def test_no_shm_profile_creates_no_segment(rig_factory, resilience, record_trial, trial_plan):
    [(index, seed)] = trial_plan(1, 1)
    resilience.describe(
        fault="none",
        profile="per-node",
        mitigations={"fastdds_profile": "no-shm"},
        claim="under fixtures/fastdds_no_shm.xml no /dev/shm/fastrtps_* file is created",
    )
    before = shm.segments()
    rig = rig_factory("per-node")
    rig.client.load_ok("cloneguard", "cloneguard::Talker")
    created = shm.segments() - before
    record_trial(
        index,
        seed,
        Outcome(TrialOutcome.SURVIVED if not created else TrialOutcome.FAILED, details={"created": sorted(created)}),
    )
    resilience.expect_rate(TrialOutcome.SURVIVED, at_least=1.0)


def test_graceful_stop_with_shm_leaks_nothing(rig_factory, resilience, record_trial, trial_plan):
    [(index, seed)] = trial_plan(1, 1)
    resilience.describe(
        fault="sigterm-container",
        profile="per-node",
        mitigations={"fastdds_profile": "shm"},
        claim="with the SHM transport on, a graceful stop (SIGTERM) removes every "
        "segment the container and its children made",
    )
    before = shm.segments()
    rig = rig_factory("per-node", fastdds_profile=SHM_PROFILE)
    rig.client.load_ok("cloneguard", "cloneguard::Talker")
    # Only what this container maps: another session may make segments meanwhile.
    created = shm.belonging_to(shm.segments() - before, rig.proc.record_shm())
    rig.client.close()
    rig.proc.signal(signal.SIGTERM)
    code = rig.proc.wait(timeout=10)
    left = shm.segments() & created
    ok = created and not left and code == 0
    record_trial(
        index,
        seed,
        Outcome(
            TrialOutcome.SURVIVED if ok else TrialOutcome.FAILED,
            details={"created": len(created), "left": sorted(left), "exit_code": code},
        ),
    )
    resilience.expect_rate(TrialOutcome.SURVIVED, at_least=1.0)


class _Named:
    """A container factory whose containers take their own node name: two
    containers both called /ComponentManager on one domain would each
    answer the other's client, and the victim's nodes could land in the
    bystander."""

    def __init__(self, factory, node_name: str):
        self._factory = factory
        self._node_name = node_name

    def start(self, args, **kwargs):
        return self._factory.start(args, node_name=self._node_name, **kwargs)

    def connect(self, proc):
        return self._factory.connect(proc)


def test_sigkilled_container_leaves_orphans_that_are_found_and_removed(
    container_factory, rig_factory, resilience, record_trial, trial_plan
):
    [(index, seed)] = trial_plan(1, 1)
    resilience.describe(
        fault="sigkill-container",
        profile="per-node",
        mitigations={"fastdds_profile": "shm"},
        claim="a SIGKILLed container leaves orphaned SHM segments; the harness finds "
        "them the way Fast DDS does (their lock files can be locked) and removes "
        "only those, leaving the segments of a live container alone; the ports the "
        "death orphans in a live peer (lock-less: found by no live process mapping "
        "them) are removed once that peer has stopped, so none is left",
    )
    before = shm.segments()
    bystander = Rig(_Named(container_factory, "bystander"), "per-node", fastdds_profile=SHM_PROFILE)
    victim = rig_factory("per-node", fastdds_profile=SHM_PROFILE)
    victim.client.load_ok("cloneguard", "cloneguard::Talker")
    # The spare made after the load has its own participant and ports: seen
    # mapped only once made (else one orphan of the victim's is not ours).
    rest.wait_for_spare(victim.client.node, victim.proc.pid)
    victim.client.close()
    # What the bystander owns (holds the lock of): nothing of it may go while it lives.
    bystanders_own = {
        seg.name: seg.files
        for seg in shm.classify(shm.locked_by(set(bystander.proc.group_members())))
        if not set(seg.files) & before
    }
    ours = victim.proc.record_shm()  # what it maps: the only candidates
    sigkill_container(victim.proc)
    victim.proc.wait(timeout=10)
    # Its node processes die of PR_SET_PDEATHSIG right after it.
    victim_gone = procfs.wait_group_empty(victim.proc.pgid, timeout=10)

    # While the bystander lives: the victim's orphans go, nothing it owns.
    candidates = shm.segments() - before
    removed = shm.remove_orphans_of(candidates, ours)
    present = shm.segments()
    kept = bool(bystanders_own) and all(set(files) <= present for files in bystanders_own.values())
    # Until it drops the dead participants, the bystander probes their ports'
    # lock files, and removes and re-creates ports it sends to: the victim's
    # ports are judged after it stops. Its participant segments now.
    left_orphans = [
        seg.name
        for seg in shm.classify(present - before)
        if seg.orphan and seg.name in ours and not seg.name.startswith("fastrtps_port")
    ]
    went_on = bystander.goes_on()

    # The victim died holding references to the bystander's ports, so the
    # bystander leaves them behind with no lock file when it stops, and ports
    # of the victim it had open to send to as well. The scenario stops it
    # (gracefully, and waits for its whole group) before its last clean-up,
    # so the leftovers check after the test finds nothing of it.
    bystander.client.close()
    stopped = bystander.proc.stop()
    bystander_gone = procfs.wait_group_empty(bystander.proc.pgid, timeout=10)
    owners = victim.proc.shm_seen | bystander.proc.shm_seen
    late = shm.remove_orphans_of(shm.segments() - before, owners)
    still_orphaned = [seg.name for seg in shm.classify(shm.segments() - before) if seg.orphan and seg.name in owners]

    ok = (
        victim_gone
        and removed
        and kept
        and not left_orphans
        and went_on is None
        and bystander_gone
        and not still_orphaned
    )
    record_trial(
        index,
        seed,
        Outcome(
            TrialOutcome.SURVIVED if ok else TrialOutcome.FAILED,
            details={
                "orphans_removed": [s.name for s in removed],
                "bystanders_own_kept": len(bystanders_own) if kept else False,
                "orphans_left": left_orphans,
                "bystander": went_on or "went on",
                "bystander_stop_forced": stopped.forced,
                "late_orphans_removed": [s.name for s in late],
                "orphans_left_at_end": still_orphaned,
            },
        ),
    )
    resilience.note(
        f"{len(removed)} orphaned segment(s) removed while the bystander ran; its "
        f"{len(bystanders_own)} own segment(s) kept"
    )
    resilience.note(
        f"{len(late)} segment(s) orphaned by the death, left when the bystander stopped "
        f"({sum(s.lockless for s in late)} lock-less port(s)), removed after it"
    )
    resilience.expect_rate(TrialOutcome.SURVIVED, at_least=1.0)
