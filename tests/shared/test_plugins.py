"""Parts found through entry points: swarmmap's own, and packages laid on sys.path as pip lays them
(a module beside its .dist-info with entry_points.txt), whole, broken or clashing."""

from __future__ import annotations

import textwrap
import time

import numpy as np
import pytest

from swarmmap.services.learner.consensus import consensus_rule
from swarmmap.services.learner.settings import ConsensusSettings
from swarmmap.shared import plugins
from swarmmap.shared.run.config import ConfigError, apply_override, resolve
from swarmmap.shared.run.fingerprint import settings_fingerprint
from swarmmap.shared.world.datasets import DatasetError, read_log

RULE = '''
from pydantic import BaseModel
from swarmmap.shared.plugins import ConsensusPlugin, DatasetReader

class Options(BaseModel):
    model_config = {"extra": "forbid"}
    pull: float = 0.5

class Rule:
    def __init__(self, pull): self.pull = pull
    def start_round(self, k, theta, extra): pass
    def keep_for(self, rounds, timed): return rounds
    def targets(self, ages, th_i, thj, extras): return (thj + th_i) / 2, None
    def dual_step(self, rho, th_i, th_j, z, a): return self.pull * rho * (th_i - th_j)
    def data_loss(self, node): return node.batch_loss()
    def extra(self): return []

class Half:  # a rule without dual_step or data_loss
    def start_round(self, k, theta, extra): pass

GOOD = ConsensusPlugin(lambda model, s: Rule(s.options.pull), "a test rule", options=Options)
FOURIER_ONLY = ConsensusPlugin(lambda model, s: Rule(1.0), "works on FourierNets", models=("fourier",), why_models="counts frequencies")
HALF = ConsensusPlugin(lambda model, s: Half(), "a rule that lacks methods")
NOT_A_SPEC = 42

def _read(path, pose, topics):
    import numpy as np
    from swarmmap.shared.world.datasets import LaserLog
    a = np.loadtxt(path, delimiter=",", ndmin=2)
    return LaserLog(str(path), a[:, 0], a[:, 1:4], np.linspace(-1.5, 1.5, a.shape[1] - 4), a[:, 4:], 10.0)

READER = DatasetReader(lambda p: p.name.endswith(".scans.txt"), _read, "a test log (*.scans.txt)")
WRONG_READER = DatasetReader(lambda p: p.name.endswith(".wrong"), lambda p, pose, topics: [1, 2], "returns a list")
'''


def config(*sets: str):
    """The smoke preset's config with these ``--set`` overrides."""
    tree: dict = {}
    for item in sets:
        apply_override(tree, item)
    return resolve(tree, preset="smoke", environ={})


@pytest.fixture
def install(tmp_path, monkeypatch):
    """Lay a package on sys.path as pip would: its module and a .dist-info naming its entry points."""

    def lay(name: str, version: str, entry_points: dict[str, dict[str, str]], module: str, source: str):
        site = tmp_path / f"site-{name}"
        info = site / f"{name.replace('-', '_')}-{version}.dist-info"
        info.mkdir(parents=True)
        (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n")
        (info / "entry_points.txt").write_text("".join(f"[{group}]\n" + "".join(f"{k} = {v}\n" for k, v in eps.items()) + "\n"
                                                       for group, eps in entry_points.items()))
        (site / f"{module}.py").write_text(textwrap.dedent(source))
        monkeypatch.syspath_prepend(str(site))
        plugins.refresh()

    yield lay
    monkeypatch.undo()
    plugins.refresh()


def test_swarmmaps_own_parts_are_registered_as_entry_points():
    assert plugins.names("consensus")[:4] == ["dgvi", "dinno", "ramen", "sigma"]
    assert {"carmen", "rosbag"} <= set(plugins.names("datasets"))
    assert all(p.builtin and p.package == "swarmmap" for p in plugins.installed("consensus") if p.name == "sigma")
    assert plugins.load("consensus", "sigma").models == ("bnn",)
    lines, refused = plugins.report()
    assert refused == 0 and any(line.split()[:2] == ["dinno", "swarmmap"] for line in lines)


def test_an_unknown_rule_is_refused_with_the_close_names():
    with pytest.raises(plugins.PluginError, match=r"no consensus plug-in is called 'sigm'.*did you mean 'sigma'"):
        plugins.find("consensus", "sigm")
    with pytest.raises(ConfigError, match=r"learner.consensus.*'sigm'.*did you mean 'sigma'"):
        config("learner.consensus=sigm")


def test_a_rule_from_another_package_is_chosen_by_name_with_its_own_options(install):
    install("my-rules", "1.2.0", {"swarmmap.consensus": {"half-pull": "my_rules:GOOD"}}, "my_rules", RULE)
    cfg = config("learner.consensus=half-pull", 'learner.consensus_options={"pull": 0.25}')
    settings = ConsensusSettings.of(cfg.learner)
    assert settings.options.pull == 0.25
    import torch

    rule = consensus_rule("half-pull", torch.nn.Linear(2, 1), settings)
    assert float(rule.dual_step(2.0, torch.ones(3), torch.zeros(3), None, None)[0]) == 0.5
    # its name and version join the settings fingerprint: a run resumed with another version is told so
    fp = settings_fingerprint(cfg)
    assert fp["learner.consensus_plugin"] == "my-rules 1.2.0" and fp["learner.consensus_options"] == {"pull": 0.25}
    with pytest.raises(ConfigError, match=r"consensus_options: pull: Input should be a valid number"):
        config("learner.consensus=half-pull", 'learner.consensus_options={"pull": "hard"}')
    with pytest.raises(ConfigError, match=r"consensus_options: consensus dinno takes no options \(got pull\)"):
        config('learner.consensus_options={"pull": 1}')


def test_a_built_in_rule_leaves_the_fingerprint_as_it_was():
    fp = settings_fingerprint(config())
    assert "learner.consensus_options" not in fp and "learner.consensus_plugin" not in fp and fp["learner.consensus"] == "dinno"


def test_a_rule_says_which_models_it_serves(install):
    install("my-rules", "1.0", {"swarmmap.consensus": {"freq": "my_rules:FOURIER_ONLY"}}, "my_rules", RULE)
    with pytest.raises(ConfigError, match=r"consensus freq counts frequencies: it needs model fourier \(not bnn\)"):
        config("learner.consensus=freq", "learner.model=bnn")


def test_broken_plugins_are_refused_by_name_and_package_in_seconds(install):
    install("broken-rules", "0.3", {"swarmmap.consensus": {"crashes": "no_such_module_here:RULE", "number": "broken_rules:NOT_A_SPEC",
                                                           "half": "broken_rules:HALF"}}, "broken_rules", RULE)
    start = time.monotonic()
    with pytest.raises(ConfigError, match=r"consensus plug-in 'crashes' \(no_such_module_here:RULE, from broken-rules 0.3\) "
                                          r"failed to import: ModuleNotFoundError"):
        config("learner.consensus=crashes")
    with pytest.raises(ConfigError, match=r"'number' .*from broken-rules 0.3\) breaks its contract: .* is a int, not a "
                                          r"swarmmap.shared.plugins.ConsensusPlugin"):
        config("learner.consensus=number")
    import torch

    with pytest.raises(plugins.PluginError, match=r"'half' .*broken-rules 0.3\) breaks its contract: the rule it makes has "
                                                  r"no keep_for, targets, dual_step, data_loss, extra"):
        consensus_rule("half", torch.nn.Linear(2, 1), ConsensusSettings())
    assert time.monotonic() - start < 5
    lines, refused = plugins.report()
    assert refused == 2 and sum("REFUSED" in line for line in lines) == 2


def test_two_packages_that_register_one_name_are_both_named(install):
    install("rules-a", "1.0", {"swarmmap.consensus": {"same": "rules_a:GOOD"}}, "rules_a", RULE)
    install("rules-b", "2.0", {"swarmmap.consensus": {"same": "rules_b:GOOD"}}, "rules_b", RULE)
    with pytest.raises(ConfigError, match=r"'same' is registered by more than one package \(rules-a 1.0, rules-b 2.0\)"):
        config("learner.consensus=same")


def test_a_dataset_reader_from_another_package_reads_its_format(install, tmp_path):
    install("my-readers", "0.1", {"swarmmap.datasets": {"scans-txt": "my_readers:READER", "wrong": "my_readers:WRONG_READER"}},
            "my_readers", RULE)
    log = tmp_path / "robot.scans.txt"
    np.savetxt(log, np.column_stack([np.arange(4.0), np.zeros((4, 3)), np.full((4, 5), 2.0)]), delimiter=",")
    got = read_log(log)
    assert len(got) == 4 and got.ranges.shape == (4, 5) and got.source == str(log)
    (tmp_path / "x.wrong").write_text("")
    with pytest.raises(DatasetError, match=r"'wrong' .*my-readers 0.1\) breaks its contract: its read returned a list"):
        read_log(tmp_path / "x.wrong")
    (tmp_path / "x.unknown").write_text("")
    with pytest.raises(DatasetError, match=r"not a dataset swarmmap reads: give a test log \(\*.scans.txt\), .* or a ROS 1 bag"):
        read_log(tmp_path / "x.unknown")


def test_an_attack_from_another_package_lies_as_it_says(install):
    install("my-attacks", "0.2", {"swarmmap.attacks": {"halve": "my_attacks:HALVE", "mute": "my_attacks:MUTE"}}, "my_attacks", '''
from swarmmap.shared.plugins import AttackPlugin

def halve(liar, theta):
    theta *= 0.5

HALVE = AttackPlugin(halve, "every parameter halved", models=("fourier",))
MUTE = AttackPlugin(None, "says nothing", sends="nothing")
''')
    from swarmmap.services.learner.attacks import Liar
    from swarmmap.shared.learning.layout import StateLayout

    layout = StateLayout(4, 2, tensors=(("0.weight", 0, 4),))
    v = np.arange(8, dtype=np.float32)
    assert Liar("halve", layout, 0).lie(v).tolist() == [0, 0.5, 1, 1.5, 4, 5, 6, 7]  # the parameters only
    assert config("faults.attack=halve", "faults.attackers=[1]").faults.attack == "halve"
    with pytest.raises(ConfigError, match=r"faults.attack halve \(every parameter halved\): it needs learner.model fourier"):
        config("faults.attack=halve", "faults.attackers=[1]", "learner.model=bnn")
    with pytest.raises(ConfigError, match=r"faults.attack.*no attacks plug-in is called 'halv'.*did you mean 'halve'"):
        config("faults.attack=halv")


def test_a_network_from_another_package_is_built_saved_and_loaded_by_its_name(install, tmp_path):
    install("my-nets", "3.1", {"swarmmap.models": {"wide": "my_nets:WIDE"}}, "my_nets", '''
from swarmmap.shared.plugins import ModelPlugin

def build(spec, bounds):
    from swarmmap.shared.learning.models import FourierNet
    shape = [spec.shape[0], *(2 * w for w in spec.shape[1:-1]), spec.shape[-1]]
    return FourierNet(shape, spec.scale, bounds)

WIDE = ModelPlugin(build, "a FourierNet twice as wide")
''')
    import torch

    from swarmmap.shared.learning.networks import build_network, has_std, load_model, model_kind, save_model
    from swarmmap.shared.run.config import std_models

    cfg = config("learner.model=wide", "learner.model_shape=[2,16,8,1]")
    net = build_network(cfg.network(), (0.0, 0.0, 4.0, 4.0), cfg.seed)
    assert model_kind(net) == "wide" and net.shape == [2, 32, 16, 1] and not has_std("wide") and "wide" not in std_models()
    again = build_network(cfg.network(), (0.0, 0.0, 4.0, 4.0), cfg.seed)  # every learner starts from the same network
    assert all(torch.equal(a, b) for a, b in zip(net.parameters(), again.parameters()))
    save_model(net, tmp_path / "robot-0.pt")
    back = load_model(tmp_path / "robot-0.pt")
    assert model_kind(back) == "wide" and all(torch.equal(a, b) for a, b in zip(net.state_dict().values(),
                                                                                back.state_dict().values()))
    assert settings_fingerprint(cfg)["learner.model_plugin"] == "my-nets 3.1"
    with pytest.raises(ConfigError, match=r"learner.model: no models plug-in is called 'wdie'.*did you mean 'wide'"):
        config("learner.model=wdie")
