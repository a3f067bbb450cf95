"""Opening a Zenoh session: bad settings are named, not a traceback."""

from __future__ import annotations

import pytest

from swarmmap.shared.bus import Bus
from swarmmap.shared.config import ConfigError, ZenohSettings
from swarmmap.shared.protocol import Keys


@pytest.mark.parametrize("settings, words", [
    (dict(config_file="/nonexistent/zenoh.json5", insecure=True), "No such file"),
    (dict(listen=["tcp/203.0.113.9:7447"], multicast_scouting=False, insecure=True), "203.0.113.9"),
])
def test_bad_zenoh_settings_raise_config_error(tmp_path, settings, words):
    with pytest.raises(ConfigError) as info:
        Bus.open(ZenohSettings(**settings), Keys("swarmmap", "r"), "test")
    assert "zenoh: cannot open a session" in info.value.message and words in info.value.message


def test_corrupt_zenoh_file_is_named(tmp_path):
    bad = tmp_path / "z.json5"
    bad.write_text("{ mode: 'peer', listen: [")
    with pytest.raises(ConfigError, match="z.json5"):
        Bus.open(ZenohSettings(config_file=bad, insecure=True), Keys("swarmmap", "r"), "test")
