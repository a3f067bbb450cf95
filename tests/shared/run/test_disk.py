"""The run directory's disk: a read-only or full disk is found by really writing, and named."""

from __future__ import annotations

import pytest

from swarmmap.shared.run.disk import disk_words, is_full, write_problem


@pytest.mark.integration
def test_a_read_only_disk_is_found_and_named_even_for_root(tmpfs):
    ro = tmpfs("1m", read_only=True)
    why = write_problem(ro / "run")
    assert why == f"{ro} cannot be written (Read-only file system)"
    assert disk_words(ro / "run") == f"the disk of {ro / 'run'}: tmpfs mounted at {ro}, 1.0 MB free of 1.0 MB"


@pytest.mark.integration
def test_a_full_disk_is_found_and_an_empty_one_is_not(tmpfs):
    big = tmpfs("8m")
    assert write_problem(big / "run") is None and not is_full(big)
    small = tmpfs("200k")
    assert is_full(small) and "lies on a full disk (tmpfs mounted at" in write_problem(small)
    assert list(small.iterdir()) == [], "the probe left a file behind"
