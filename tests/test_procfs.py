"""harness/procfs.py: what the harness reads of processes it started."""

import os

from cloneguard.harness import procfs


def test_lasting_fds_keep_what_stays_open_and_drop_what_closes_between_readings(monkeypatch, tmp_path):
    kept = os.open(tmp_path / "kept", os.O_CREAT | os.O_RDONLY)
    brief = os.open(tmp_path / "brief", os.O_CREAT | os.O_RDONLY)
    # The first pause between readings closes one fd: it was in the first
    # listing only, as a /proc file the container reads for a moment is.
    pauses: list[float] = []

    def pause(_seconds):
        if not pauses:
            os.close(brief)
        pauses.append(_seconds)

    monkeypatch.setattr(procfs.time, "sleep", pause)
    try:
        lasting = procfs.lasting_fds(os.getpid(), readings=3)
    finally:
        os.close(kept)
    assert lasting[kept] == str(tmp_path / "kept")
    assert str(tmp_path / "brief") not in lasting.values()
    assert len(pauses) == 2
