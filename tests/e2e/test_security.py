"""A `swarmmap up` run is closed to strangers and robust to a hostile member: a client without
the run's credentials (plain TCP, a certificate of another CA, another run's credentials)
cannot connect; with learner 1's credentials it cannot publish as learner 2; the all-zero
States it sends as learner 1 are refused by the learners, and the run ends exactly where a
clean run ends. Each service's key lies in a folder of its own and the CA key is nowhere."""

from __future__ import annotations

import json
import stat
import subprocess
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import yaml
from cryptography import x509
from cryptography.hazmat.primitives import serialization

from swarmmap.shared.learning.models import param_count
from swarmmap.shared.learning.networks import build_network
from swarmmap.shared.run.config import ConfigError, RunConfig
from swarmmap.shared.wire.bus import Bus
from swarmmap.shared.wire.protocol import Keys, State, Tensor
from swarmmap.shared.wire.secrets import CA_FILE, CERT_FILE, KEY_FILE, own_folder, router_names, write_credentials
from swarmmap.shared.wire.services import identities
from tests.conftest import SWARMMAP, clean_env, wait_until
from tests.harness import final_losses

pytestmark = pytest.mark.e2e

ARGS = ["up", "--preset", "smoke", "--robots", "3", "--rounds", "40", "--no-observer"]


def test_strangers_are_refused_and_a_hostile_member_changes_nothing(tmp_path):
    clean = subprocess.run([*SWARMMAP, *ARGS, "--run-dir", str(tmp_path / "clean")], capture_output=True, text=True,
                           timeout=300, env=clean_env())
    assert clean.returncode == 0, clean.stderr[-3000:]

    run_dir = tmp_path / "attacked"
    proc = subprocess.Popen([*SWARMMAP, *ARGS, "--run-dir", str(run_dir)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.STDOUT, env=clean_env())
    try:
        recorder_log = run_dir / "logs" / "recorder-0.log"
        assert wait_until(lambda: recorder_log.exists() and "recording run" in recorder_log.read_text(), 120, 0.2)
        cfg = RunConfig.model_validate(yaml.safe_load((run_dir / "config.yaml").read_text()))
        keys = Keys(cfg.key_prefix, cfg.run_id)
        router = cfg.zenoh.model_copy(update={"connect_timeout_s": 5})
        # A member gone rogue, from the start of the run to its end: learner 1's own credentials.
        pool = ThreadPoolExecutor(1)
        attacker = pool.submit(attack, router, keys, cfg, proc, recorder_log)
        # Meanwhile a stranger: plain TCP, then TLS with a certificate of another CA.
        with pytest.raises(ConfigError, match="cannot open a session"):
            Bus.open(router.model_copy(update={"insecure": True, "mode": "client"}), keys, "learner", 1)
        write_credentials(tmp_path / "forged", cfg.run_id, identities(3), router_names(cfg.zenoh.connect))
        with pytest.raises(ConfigError, match="cannot open a session"):
            Bus.open(router.model_copy(update={"secrets": tmp_path / "forged"}), keys, "learner", 1)
        clean_run = yaml.safe_load((tmp_path / "clean" / "config.yaml").read_text())["run_id"]
        with pytest.raises(ConfigError, match="cannot open a session"):  # a member of another run, its own credentials
            Bus.open(router.model_copy(update={"secrets": tmp_path / "clean" / "secrets"}), Keys(cfg.key_prefix, clean_run),
                     "learner", 1)
        assert attacker.result(timeout=240) > 0, "the rogue member sent nothing before the run ended"
        pool.shutdown()
        assert proc.wait(timeout=240) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["ok"], summary
    assert final_losses(run_dir) == final_losses(tmp_path / "clean"), "the hostile States changed the result"
    # Learner 1's neighbours refused its zero States; nobody ever saw learner 2's forged ones
    # (the router dropped them), so learner 2's own neighbours refused only learner 1's.
    assert summary["learners"]["0"]["refused"] > 0 and summary["learners"]["2"]["refused"] > 0
    logs = (run_dir / "logs" / "learner-0.log").read_text()
    assert "refused the state of node 1" in logs and "refused the state of node 2" not in logs
    assert_each_key_apart(run_dir, cfg.run_id)


def attack(router, keys: Keys, cfg: RunConfig, proc: subprocess.Popen, recorder_log) -> int:
    """As learner 1 (its own credentials): all-zero States of every round, as learner 1 and as
    learner 2, until the run is over; how many times it sent them."""
    size = param_count(build_network(cfg.network(), (0, 0, 1, 1), cfg.seed))
    zeros = Tensor.of(np.zeros(size, np.float32), "<f4")
    with Bus.open(router, keys, "learner", 1) as rogue:
        as_self, as_other = rogue.publisher(keys.state(1)), rogue.publisher(keys.state(2))
        deadline, sent = time.monotonic() + 120, 0
        while proc.poll() is None and time.monotonic() < deadline and "(final)" not in recorder_log.read_text():
            for k in range(cfg.learner.rounds + 1):
                as_self.put(State(run=cfg.run_id, sender=1, round=k, params=zeros))
                as_other.put(State(run=cfg.run_id, sender=2, round=k, params=zeros))
            sent += 1
            time.sleep(0.05)
    return sent


def public_der(key) -> bytes:
    return key.public_bytes(serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo)


def assert_each_key_apart(run_dir, run_id) -> None:
    """Every private key in the run directory is one service's, in its own folder (0700) beside
    its certificate; none is the CA's."""
    secrets = run_dir / "secrets"
    ca = x509.load_pem_x509_certificate((own_folder(secrets, "router-0", run_id) / CA_FILE).read_bytes())
    keys = {p: serialization.load_pem_private_key(p.read_bytes(), None) for p in run_dir.rglob("*")
            if p.is_file() and b"PRIVATE KEY" in p.read_bytes()}
    assert sorted(p.parent for p in keys) == sorted(own_folder(secrets, n, run_id) for n in identities(3)), sorted(keys)
    for path, key in keys.items():
        assert path.name == KEY_FILE and stat.S_IMODE(path.parent.stat().st_mode) == 0o700
        assert sorted(p.name for p in path.parent.iterdir()) == [CA_FILE, CERT_FILE, KEY_FILE]
        cert = x509.load_pem_x509_certificate((path.parent / CERT_FILE).read_bytes())
        assert public_der(cert.public_key()) == public_der(key.public_key()) != public_der(ca.public_key()), path
