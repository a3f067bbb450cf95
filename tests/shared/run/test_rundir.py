"""The run directory's lock: one launcher at a time."""

from __future__ import annotations


def test_one_launcher_at_a_time_holds_a_run_directory(tmp_path):
    """A second hold on a held run directory is refused naming the holder; a directory the hold
    made and left empty is removed; one with the run's files stays."""
    import pytest

    from swarmmap.shared.run.rundir import RunDirBusy, hold_run_dir

    run_dir = tmp_path / "run"
    with hold_run_dir(run_dir, "swarmmap prepare"):
        with pytest.raises(RunDirBusy, match=r"held by swarmmap prepare \(pid \d+\)"):
            with hold_run_dir(run_dir, "swarmmap up"):
                pass
    assert not run_dir.exists(), "an empty run directory made for nothing was left behind"
    with hold_run_dir(run_dir, "swarmmap up"):
        (run_dir / "config.yaml").write_text("robots: 1\n")
    with hold_run_dir(run_dir, "swarmmap up"):  # free again once the first is over
        pass
    assert (run_dir / "config.yaml").exists()
