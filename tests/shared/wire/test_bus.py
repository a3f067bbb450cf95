"""Opening a Zenoh session: bad settings are named, not a traceback."""

from __future__ import annotations

import json

import pytest

from swarmmap.shared.run.config import ConfigError, ZenohSettings
from swarmmap.shared.wire.bus import Bus, zenoh_config
from swarmmap.shared.wire.protocol import Keys


@pytest.mark.parametrize("settings, words", [
    (dict(config_file="/nonexistent/zenoh.json5", insecure=True), "No such file"),
    (dict(listen=["tcp/203.0.113.9:7447"], multicast_scouting=False, insecure=True), "203.0.113.9"),
])
@pytest.mark.integration
def test_bad_zenoh_settings_raise_config_error(tmp_path, settings, words):
    with pytest.raises(ConfigError) as info:
        Bus.open(ZenohSettings(**settings), Keys("swarmmap", "r"), "test")
    assert "zenoh: cannot open a session" in info.value.message and words in info.value.message


def test_corrupt_zenoh_file_is_named(tmp_path):
    bad = tmp_path / "z.json5"
    bad.write_text("{ mode: 'peer', listen: [")
    with pytest.raises(ConfigError, match="z.json5"):
        Bus.open(ZenohSettings(config_file=bad, insecure=True), Keys("swarmmap", "r"), "test")


def test_zenoh_shared_memory_is_zenohs_default_unless_set():
    """Zenoh passes a large message between processes of one machine through /dev/shm, which
    network namespaces share: ``zenoh.shared_memory=false`` keeps every byte on the links (what
    bench/links.py sets under ``up --netns``); unset, Zenoh's default (on) stands."""
    off = ZenohSettings(insecure=True, shared_memory=False)
    assert json.loads(zenoh_config(off, "learner-0").get_json("transport/shared_memory"))["enabled"] is False
    assert json.loads(zenoh_config(ZenohSettings(insecure=True), "learner-0").get_json("transport/shared_memory"))["enabled"] is True
