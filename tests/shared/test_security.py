"""A run's credentials and the router's access policy, on real Zenoh sessions over mutual TLS:
strangers cannot connect, members can publish only on their own keys."""

from __future__ import annotations

import stat

import pytest
from cryptography import x509
from cryptography.hazmat.primitives.asymmetric import ec

from swarmmap.shared.bus import Bus
from swarmmap.shared.config import ConfigError, ZenohSettings
from swarmmap.shared.protocol import Keys, RoundComplete, State, Tensor
from swarmmap.shared.secrets import access_policy, identities, write_secrets
from tests.conftest import free_port, wait_until


@pytest.fixture
def run(tmp_path, run_id):
    keys = Keys("swarmmap", run_id)
    folder = tmp_path / "secrets"
    write_secrets(folder, 3, access_policy(keys, 3))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = Bus.open(ZenohSettings(mode="router", listen=[endpoint], multicast_scouting=False, secrets=folder), keys, "router", 0)
    client = ZenohSettings(connect=[endpoint], multicast_scouting=False, secrets=folder, connect_timeout_s=5)
    yield keys, folder, client
    router.close()


def test_every_identity_gets_a_certificate_of_the_runs_ca_readable_by_its_owner_alone(tmp_path):
    folder = tmp_path / "s"
    names = write_secrets(folder, 2, {"enabled": True})
    assert set(names) == {"router-0", "recorder-0", "observer-0", "world-0", "up-0", "status-0",
                          "lidar-0", "lidar-1", "learner-0", "learner-1"}
    ca = x509.load_pem_x509_certificate((folder / "ca.pem").read_bytes())
    for name in names:
        cert = x509.load_pem_x509_certificate((folder / f"{name}.pem").read_bytes())
        assert cert.subject.get_attributes_for_oid(x509.oid.NameOID.COMMON_NAME)[0].value == name
        ca.public_key().verify(cert.signature, cert.tbs_certificate_bytes, ec.ECDSA(cert.signature_hash_algorithm))
        for suffix in (".pem", ".key"):
            assert stat.S_IMODE((folder / f"{name}{suffix}").stat().st_mode) == 0o600
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    before = (folder / "ca.pem").read_bytes()
    write_secrets(folder, 3, {"enabled": True})  # more robots later: same CA, new certificates added
    assert (folder / "ca.pem").read_bytes() == before and (folder / "learner-2.pem").exists()
    assert len(identities(3)) == 12


def test_a_member_publishes_only_on_its_own_keys(run):
    keys, folder, client = run
    got: list[tuple[str, int]] = []

    def on_state(m: State) -> None:
        got.append((f"state-{m.sender}", m.round))

    with Bus.open(client, keys, "recorder", 0) as listener, Bus.open(client, keys, "learner", 1) as learner1:
        listener.subscribe(keys.state("*"), State, on_state)
        listener.subscribe(keys.round_complete("*"), RoundComplete, lambda m: got.append(("complete", m.round)))
        listener.announce()
        assert wait_until(lambda: ("recorder", "0") in learner1.alive("recorder"), 10)
        params = Tensor.of([1.0, 2.0], "<f4")
        learner1.publisher(keys.state(2)).put(State(run=keys.run, sender=2, round=7, params=params))  # as learner 2
        learner1.publisher(keys.state(1)).put(State(run=keys.run, sender=1, round=3, params=params))  # its own
        learner1.publisher(keys.round_complete(1)).put(RoundComplete(run=keys.run, sender=1, round=3))
        assert wait_until(lambda: {("state-1", 3), ("complete", 3)} <= set(got), 10)  # its own keys came through
    assert sorted(got) == [("complete", 3), ("state-1", 3)], "the router let learner 1 speak as learner 2"


def test_strangers_cannot_connect(run, tmp_path):
    keys, folder, client = run
    with pytest.raises(ConfigError, match="cannot open a session"):  # no certificate at all: plain TCP
        Bus.open(client.model_copy(update={"insecure": True, "mode": "client"}), keys, "learner", 1)
    other = tmp_path / "other"
    write_secrets(other, 3, {"enabled": True})  # a certificate of another CA
    with pytest.raises(ConfigError, match="cannot open a session"):
        Bus.open(client.model_copy(update={"secrets": other}), keys, "learner", 1)


def test_missing_credentials_are_named(tmp_path):
    with pytest.raises(ConfigError, match="swarmmap secrets"):
        Bus.open(ZenohSettings(connect=["tcp/127.0.0.1:1"]), Keys("swarmmap", "r"), "learner", 0)
    with pytest.raises(ConfigError, match="learner-9 has no credentials"):
        write_secrets(tmp_path / "s", 2, {"enabled": True})
        Bus.open(ZenohSettings(connect=["tcp/127.0.0.1:1"], secrets=tmp_path / "s"), Keys("swarmmap", "r"), "learner", 9)


HOSTILE_PUTS = [  # (identity, forbidden key, what it would forge) -- the attacks, by a member
    ("learner-1", "learners/2/metrics", "Metrics(final=True) as another learner"),
    ("learner-1", "learners/2/state", "a State as another learner"),
    ("learner-1", "robots/1/samples", "Samples(last=True) ending its own robot's data collection"),
    ("learner-1", "robots/0/scan", "a LiDAR scan in the world's name"),
    ("learner-1", "run/done", "the end of the run"),
    ("lidar-0", "robots/1/samples", "another robot's training points"),
    ("observer-0", "learners/0/state", "a State from a listener"),
]
OWN_KEY = {"learner-1": "learners/1/metrics", "lidar-0": "robots/0/samples", "observer-0": "alive/observer/0"}


@pytest.mark.parametrize("who, key, forged", HOSTILE_PUTS, ids=[f"{w}:{k}" for w, k, _ in HOSTILE_PUTS])
def test_a_member_cannot_forge_what_is_not_its_own(run, who, key, forged):
    keys, folder, client = run
    got: list[str] = []
    service, ident = who.rsplit("-", 1)
    with Bus.open(client, keys, "recorder", 0) as listener, Bus.open(client, keys, service, ident) as rogue:
        listener.session.declare_subscriber(f"{keys.root}/**", lambda sample: got.append(str(sample.key_expr)[len(keys.root) + 1:]))
        canary = OWN_KEY[who]
        wait_until(lambda: bool(listener.alive("recorder")), 5)
        deadline_ok = wait_until(lambda: (rogue.session.put(f"{keys.root}/{key}", b"forged"),
                                          rogue.session.put(f"{keys.root}/{canary}", b"canary"),
                                          canary in got)[-1], 10, 0.2)
    assert deadline_ok, f"{who}'s own key {canary} never arrived: the test proves nothing"
    assert key not in got, f"{who} could forge {forged} on {key}"


def test_only_the_world_answers_the_map_query(run):
    keys, folder, client = run
    with Bus.open(client, keys, "learner", 1) as rogue, Bus.open(client, keys, "world", 0) as world, \
            Bus.open(client, keys, "observer", 0) as asker:
        rogue.session.declare_queryable(keys.world_map(), lambda q: q.reply(keys.world_map(), b"a false validation set"))
        world.session.declare_queryable(keys.world_map(), lambda q: q.reply(keys.world_map(), b"the map"))
        answers: list[bytes] = []
        assert wait_until(lambda: bool(answers.extend(r.ok.payload.to_bytes() for r in asker.session.get(keys.world_map(),
                                                                                                     timeout=2.0)
                                                      if r.ok is not None) or answers), 10, 0.2)
    assert set(answers) == {b"the map"}, answers
