"""Config precedence (defaults < preset < file < environment < command line) and refusals."""

from __future__ import annotations

import pytest

from swarmmap.services.cli import build_parser
from swarmmap.shared.run.config import (
    LAUNCHER_VARIABLES,
    PRESETS,
    ConfigError,
    RunConfig,
    env_names,
    parse_shape,
    resolve,
)
from swarmmap.shared.run.flags import config_from_args


def load(argv, environ=None, preset=None) -> RunConfig:
    return config_from_args(build_parser().parse_args(argv), environ=environ or {}, preset=preset)


def test_defaults_validate():
    cfg = resolve(environ={})
    assert cfg.learner.rounds == 200 and cfg.zenoh.mode is None


def test_precedence_file_env_cli(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("seed: 1\nlearner:\n  rounds: 11\n  batch_size: 100\n  lr_start: 0.5\n")
    env = {"SWARMMAP_LEARNER__ROUNDS": "22", "SWARMMAP_LEARNER__BATCH_SIZE": "200", "SWARMMAP_SEED": "2"}
    cfg = load(["learner", "--config", str(f), "--rounds", "33"], env)
    assert cfg.learner.rounds == 33  # CLI beats env and file
    assert cfg.learner.batch_size == 200  # env beats file
    assert cfg.learner.lr_start == 0.5  # file beats defaults
    assert cfg.seed == 2


def test_environment_values_lists_as_yaml_null_unsets_and_a_section_merges_field_by_field(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("run_dir: somewhere\nzenoh:\n  connect: [tcp/10.0.0.1:7447]\n  mode: client\n")
    env = {"SWARMMAP_RUN_DIR": "null", "SWARMMAP_ZENOH__CONNECT": "[tcp/10.0.0.2:7447, tcp/10.0.0.3:7447]",
           "SWARMMAP_LEARNER__CONSENSUS_OPTIONS": "{}", "SWARMMAP_RUN_ID": "007", "SWARMMAP_UID": "1000"}
    cfg = resolve(config_file=f, environ=env)
    assert cfg.run_dir is None  # null unsets what the file set
    assert cfg.zenoh.connect == ["tcp/10.0.0.2:7447", "tcp/10.0.0.3:7447"] and cfg.zenoh.mode == "client"
    assert cfg.run_id == "007"  # a text field keeps its text
    with pytest.raises(ConfigError, match="zenoh.connect: must be a list"):
        resolve(environ={"SWARMMAP_ZENOH__CONNECT": "[tcp/10.0.0.2:7447"})


def test_preset_sits_under_the_file(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("learner:\n  rounds: 7\n")
    cfg = load(["up", "--preset", "smoke", "--config", str(f)])
    assert cfg.learner.rounds == 7
    assert cfg.robots == PRESETS["smoke"]["robots"]
    assert cfg.preset == "smoke"


def test_zenoh_settings_from_cli_and_set():
    cfg = load(["world", "--zenoh-mode", "client", "--zenoh-connect", "tcp/127.0.0.1:7447",
                "--no-zenoh-multicast-scouting", "--set", "world.lidar_beams=90"])
    assert cfg.zenoh.mode == "client" and cfg.zenoh.connect == ["tcp/127.0.0.1:7447"]
    assert cfg.zenoh.multicast_scouting is False and cfg.world.lidar_beams == 90


def test_wrong_choice_names_field_and_allowed_values():
    with pytest.raises(ConfigError) as info:
        load(["learner", "--optimizer", "adan"])
    assert "learner.optimizer" in info.value.message
    assert "'adam', 'adamw' or 'sgd'" in info.value.message and "adan" in info.value.message


def test_wrong_number_and_unknown_field_in_file(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("learner:\n  roundz: 3\n  rounds: -1\n")
    with pytest.raises(ConfigError) as info:
        load(["learner", "--config", str(f)])
    assert "learner.roundz" in info.value.message and "learner.rounds" in info.value.message


def test_bad_env_value_is_named():
    with pytest.raises(ConfigError) as info:
        load(["learner"], {"SWARMMAP_LEARNER__BATCH_SIZE": "many"})
    assert "learner.batch_size" in info.value.message


def test_unknown_preset_and_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="unknown preset 'huge'"):
        load(["up", "--preset", "huge"])
    with pytest.raises(ConfigError, match="does not exist"):
        load(["up", "--config", str(tmp_path / "nope.yaml")])


def test_run_id_cannot_inject_key_wildcards():
    with pytest.raises(ConfigError, match="run_id"):
        load(["world", "--run-id", "a/*"])


def test_dumped_config_loads_back(tmp_path):
    cfg = load(["up", "--preset", "smoke", "--seed", "5"])
    f = tmp_path / "config.yaml"
    f.write_text(cfg.dump_yaml())
    assert load(["learner", "--config", str(f)]) == cfg


@pytest.mark.integration
def test_cli_exits_2_with_message(capsys):
    from swarmmap.services.cli import main

    assert main(["world", "--set", "world.lidar_beams=0"]) == 2
    assert "world.lidar_beams" in capsys.readouterr().err


def test_record_and_replay_exclude_each_other():
    with pytest.raises(ConfigError, match="up: .*record and replay exclude each other"):
        load(["up", "--record", "a", "--replay", "b"])


def test_centralized_needs_the_inproc_transport():
    with pytest.raises(ConfigError, match="transport to inproc"):
        load(["up", "--algorithm", "centralized"])


def test_the_prior_on_unseen_space_needs_a_bayesian_network():
    with pytest.raises(ConfigError, match="needs model bnn"):
        load(["up", "--model", "dropout", "--set", "learner.unseen_weight=0.05"])
    assert load(["up", "--model", "dropout", "--set", "learner.dropout_p=0.3"]).learner.dropout_p == 0.3
    with pytest.raises(ConfigError, match="dropout_p"):
        load(["up", "--model", "dropout", "--set", "learner.dropout_p=1"])


def test_dinno_fast_keeps_dinnos_setting_and_changes_only_the_schedule():
    fast, published = load(["up", "--preset", "dinno-fast"]), load(["up", "--preset", "dinno"])
    assert fast.world == published.world and fast.lidar == published.lidar and fast.robots == published.robots
    changed = {k for k, v in fast.learner.model_dump().items() if published.learner.model_dump()[k] != v}
    assert changed == {"rounds", "batch_size", "lr_start", "lr_finish", "rho_init"}
    assert published.learner.rho_init == 0.3 and published.learner.batch_size == 12500  # DiNNO's, as published


def test_a_misspelt_environment_variable_is_refused_naming_it_and_the_closest_name():
    with pytest.raises(ConfigError) as info:
        load(["up"], {"SWARMMAP_LERNER__ROUNDS": "3"})
    assert "SWARMMAP_LERNER__ROUNDS" in info.value.message and "did you mean 'SWARMMAP_LEARNER__ROUNDS'" in info.value.message
    with pytest.raises(ConfigError, match="SWARMMAP_LEARNER__ROUDS.*SWARMMAP_LEARNER__ROUNDS"):
        load(["learner"], {"SWARMMAP_LEARNER__ROUDS": "3"})
    with pytest.raises(ConfigError, match="SWARMMAP_SEDE"):
        load(["world"], {"SWARMMAP_SEDE": "1"})


def test_the_launchers_own_variables_are_accepted_and_are_no_config_fields():
    env = {name: "1" for name in LAUNCHER_VARIABLES}
    assert {"SWARMMAP_UID", "SWARMMAP_GID", "SWARMMAP_RUNS"} <= env.keys()
    assert load(["up"], {**env, "SWARMMAP_LEARNER__ROUNDS": "9"}).learner.rounds == 9
    assert not set(LAUNCHER_VARIABLES) & set(env_names()), "a launcher variable would also set a config field"


def test_unknown_fields_and_sections_name_the_closest_one(tmp_path):
    with pytest.raises(ConfigError, match=r"lerner: unknown .*did you mean 'learner'"):
        load(["up", "--set", "lerner.rounds=5"])
    with pytest.raises(ConfigError, match=r"learner.rouds: unknown field \(did you mean 'rounds'\?\)"):
        load(["up", "--set", "learner.rouds=5"])
    f = tmp_path / "c.yaml"
    f.write_text("world:\n  floorplna: procedural\n")
    with pytest.raises(ConfigError, match="world.floorplna: .*did you mean 'floorplan'"):
        load(["world", "--config", str(f)])
    with pytest.raises(ConfigError, match="did you mean 'smoke'"):
        load(["up", "--preset", "smok"])
    with pytest.raises(ConfigError, match=r"'adam', 'adamw' or 'sgd' \(got 'adan'\) \(did you mean 'adam'\?\)"):
        load(["learner", "--optimizer", "adan"])


def test_refusals_are_in_plain_words_without_pydantic_dumps_or_links():
    for argv in (["up", "--set", "faults.link_success=1.5"], ["up", "--rounds", "many"], ["up", "--set", "lerner.rounds=5"],
                 ["up", "--set", "learner.model_shape=[3,64,1]"], ["up", "--robots", "0"]):
        with pytest.raises(ConfigError) as info:
            load(argv)
        text = info.value.message
        assert "http" not in text and "validation error" not in text and "Input should" not in text, text
        assert "type=" not in text and "Value error" not in text, text
    with pytest.raises(ConfigError, match=r"faults.link_success: must be at most 1.0 \(got 1.5\)"):
        load(["up", "--set", "faults.link_success=1.5"])
    with pytest.raises(ConfigError, match=r"learner.rounds: must be a whole number \(got 'many'\)"):
        load(["up", "--rounds", "many"])


def test_a_model_shape_has_one_syntax_on_the_command_line_in_the_environment_and_in_files(tmp_path):
    want = [2, 64, 32, 1]
    assert load(["up", "--set", "learner.model_shape=[2,64,32,1]"]).learner.model_shape == want
    assert load(["up", "--set", "learner.model_shape=2,64,32,1"]).learner.model_shape == want
    assert load(["learner", "--model-shape", "2", "64", "32", "1"]).learner.model_shape == want
    assert load(["learner", "--model-shape", "2,64,32,1"]).learner.model_shape == want
    assert load(["up"], {"SWARMMAP_LEARNER__MODEL_SHAPE": "2,64,32,1"}).learner.model_shape == want
    f = tmp_path / "c.yaml"
    f.write_text("learner:\n  model_shape: [2, 64, 32, 1]\n")
    assert load(["learner", "--config", str(f)]).learner.model_shape == want
    assert parse_shape("[2, 64, 32, 1]") == parse_shape("2,64,32,1") == parse_shape(["2", "64", "32", "1"]) == want
    with pytest.raises(ConfigError, match=r"learner.model_shape: a model shape is a list of layer widths like 2,64,32,1"):
        load(["up", "--set", "learner.model_shape=2,sixty,1"])


@pytest.mark.parametrize("cli,why", [
    ({"explore": {"policy": "uncertainty"}}, "needs a model with a std: learner.model fourier has none"),
    ({"explore": {"policy": "frontier", "starts": "1,2;3,4"}}, "gives 2 start.s. for 3 robot"),
    ({"explore": {"policy": "frontier", "starts": "1,2;3,4;x,5"}}, "'x,5' is no \"x,y\" pair"),
    ({"explore": {"policy": "planned"}, "world": {"dataset": ["a.log"]}}, "world.dataset"),
    ({"explore": {"policy": "frontier"}, "learner": {"rounds": 10}}, "no goal before round decide_every 10"),
    ({"explore": {"policy": "frontier"}, "learner": {"exchange_every_s": 2.0}}, "exchange_every_s"),
    ({"explore": {"policy": "frontier"}, "ros2": {"namespaces": ["a", "b", "c"]}}, "no ros2.extent"),
    ({"explore": {"policy": "planned"}, "ros2": {"namespaces": ["a", "b", "c"], "extent": "0,0,5,5"}}, "no planned paths"),
    ({"explore": {"policy": "frontier", "starts": "1,2;3,4;5,6"}, "ros2": {"namespaces": ["a", "b", "c"],
                                                                          "extent": "0,0,5,5"}}, "start where they are"),
])
def test_an_exploration_that_cannot_run_is_refused_naming_why(cli, why):
    with pytest.raises(ConfigError, match=why):
        resolve(cli, preset="smoke", environ={})
    ok = resolve({"explore": {"policy": "uncertainty", "starts": "1,2; 3,4 ;5,6"}}, preset="quickstart", environ={})
    assert ok.explore.active and not resolve(preset="smoke", environ={}).explore.active


@pytest.mark.parametrize("ros2,why", [
    ({"extent": "0,0,5"}, r"ros2.extent: '0,0,5' is no \"xmin,ymin,xmax,ymax\""),
    ({"extent": "0,0,-5,5"}, "xmax must exceed xmin"),
    ({"extent": "0,0,5,5;1,1,2,2"}, "one box"),
    ({"namespaces": ["a", "b"], "initial_poses": "1,2,0"}, r"ros2.initial_poses gives 1 pose\(s\) for 2 robot"),
    ({"namespaces": ["a"], "initial_poses": "1,2,inf"}, "not finite"),
])
def test_ros2_frames_that_cannot_be_read_are_refused_naming_the_field(ros2, why):
    with pytest.raises(ConfigError, match=why):
        resolve({"ros2": ros2}, preset="smoke", environ={})
    ok = resolve({"ros2": {"namespaces": ["a", "b"], "initial_poses": "1,2,0; -1,0.5,3.14", "extent": "-2,-2,8,6"}},
                 preset="smoke", environ={})
    assert ok.ros2.poses() == [(1.0, 2.0, 0.0), (-1.0, 0.5, 3.14)]
