"""A run's credentials and the router's access policy, on real Zenoh sessions over mutual TLS:
strangers and other runs cannot connect, the router's name is checked, every listener is TLS,
each service holds only its own key, and members publish and read only their own keys."""

from __future__ import annotations

import socket
import stat

import pytest
from cryptography import x509
from cryptography.hazmat.primitives.asymmetric import ec

from swarmmap.shared.run.config import ConfigError, ZenohSettings
from swarmmap.shared.wire.bus import Bus, zenoh_config
from swarmmap.shared.wire.protocol import Keys, RoundComplete, State, Tensor
from swarmmap.shared.wire.secrets import (
    CA_FILE,
    CERT_FILE,
    KEY_FILE,
    Authority,
    SecretsError,
    access_policy,
    cert_name,
    own_folder,
    pem_key,
    router_names,
    write_credentials,
    write_own,
)
from swarmmap.shared.wire.services import identities
from tests.conftest import free_port, wait_until

pytestmark = pytest.mark.timeout(120)
ROBOTS = 3
NEIGHBOURS = {0: {1}, 1: {0, 2}, 2: {1}}  # a line: learner 0 may not read learner 2's State


def start_router(folder, keys, endpoint, listen=None):
    listen = [endpoint] if listen is None else listen
    settings = ZenohSettings(mode="router", listen=listen, multicast_scouting=False, secrets=folder)
    return Bus.open(settings, keys, "router", 0, policy=access_policy(keys, ROBOTS, neighbours=NEIGHBOURS))


@pytest.fixture
def run(tmp_path, run_id):
    keys = Keys("swarmmap", run_id)
    folder = tmp_path / "secrets"
    write_credentials(folder, run_id, identities(ROBOTS), router_names(["tcp/127.0.0.1:1"]))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = start_router(folder, keys, endpoint)
    client = ZenohSettings(connect=[endpoint], multicast_scouting=False, secrets=folder, connect_timeout_s=5)
    yield keys, folder, client
    router.close()


def private_keys_in(folder):
    """Every private key written anywhere under ``folder``, as public-key bytes."""
    from cryptography.hazmat.primitives import serialization

    found = []
    for path in folder.rglob("*"):
        if path.is_file() and b"PRIVATE KEY" in path.read_bytes():
            key = serialization.load_pem_private_key(path.read_bytes(), None)
            found.append((path, key.public_key().public_bytes(serialization.Encoding.DER,
                                                              serialization.PublicFormat.SubjectPublicKeyInfo)))
    return found


def test_each_service_gets_a_folder_of_its_own_and_the_ca_key_is_gone(tmp_path):
    folder = tmp_path / "s"
    names = write_credentials(folder, "r1", identities(2), router_names(["tcp/node7:7447"]))
    assert set(names) == {"router-0", "recorder-0", "observer-0", "world-0", "up-0", "status-0",
                          "lidar-0", "lidar-1", "learner-0", "learner-1"}
    assert sorted(p.name for p in folder.iterdir()) == sorted(cert_name(n, "r1") for n in names)
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    ca = x509.load_pem_x509_certificate((own_folder(folder, "router-0", "r1") / CA_FILE).read_bytes())
    for name in names:
        own = own_folder(folder, name, "r1")
        assert sorted(p.name for p in own.iterdir()) == [CA_FILE, CERT_FILE, KEY_FILE]  # its own key, nobody else's
        assert stat.S_IMODE(own.stat().st_mode) == 0o700
        assert all(stat.S_IMODE(p.stat().st_mode) == 0o600 for p in own.iterdir())
        cert = x509.load_pem_x509_certificate((own / CERT_FILE).read_bytes())
        assert cert.subject.get_attributes_for_oid(x509.oid.NameOID.COMMON_NAME)[0].value == f"{name}@r1"
        ca.public_key().verify(cert.signature, cert.tbs_certificate_bytes, ec.ECDSA(cert.signature_hash_algorithm))
        usage = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
        assert (x509.oid.ExtendedKeyUsageOID.SERVER_AUTH in usage) == (name == "router-0"), f"{name} may act as a server"
    sans = own_folder(folder, "router-0", "r1") / CERT_FILE
    names_of_router = x509.load_pem_x509_certificate(sans.read_bytes()).extensions.get_extension_for_class(
        x509.SubjectAlternativeName).value
    assert "node7" in names_of_router.get_values_for_type(x509.DNSName)
    assert private_keys_in(folder) and all(path.name == KEY_FILE for path, _ in private_keys_in(folder))
    assert ca.public_key().public_bytes(*_der()) not in {k for _, k in private_keys_in(folder)}, "the CA key was written"


def _der():
    from cryptography.hazmat.primitives import serialization

    return serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo


def test_more_credentials_later_need_the_kept_ca_which_lives_apart(tmp_path):
    folder, kept = tmp_path / "s", tmp_path / "ca"
    write_credentials(folder, "r1", identities(2), [], keep_ca=kept)
    assert sorted(p.name for p in kept.iterdir()) == ["r1.ca.key", "r1.ca.pem"] and stat.S_IMODE(kept.stat().st_mode) == 0o700
    assert write_credentials(folder, "r1", identities(3), [], keep_ca=kept) == ["lidar-2", "learner-2"]
    ca = (own_folder(folder, "learner-0", "r1") / CA_FILE).read_bytes()
    assert (own_folder(folder, "learner-2", "r1") / CA_FILE).read_bytes() == ca  # the same CA: running services trust them
    with pytest.raises(SecretsError, match="no kept CA key"):  # without the kept CA nobody can add one
        write_credentials(tmp_path / "t", "r2", identities(2), [])
        write_credentials(tmp_path / "t", "r2", identities(3), [])


def test_runs_sharing_a_folder_keep_apart(tmp_path):
    folder = tmp_path / "shared"
    write_credentials(folder, "a", identities(1), [])
    write_credentials(folder, "b", identities(1), [])
    ca_a = (own_folder(folder, "learner-0", "a") / CA_FILE).read_bytes()
    ca_b = (own_folder(folder, "learner-0", "b") / CA_FILE).read_bytes()
    assert ca_a != ca_b, "two runs in one folder share a CA"


@pytest.mark.integration
def test_a_member_publishes_only_on_its_own_keys(run):
    keys, folder, client = run
    got: list[tuple[str, int]] = []

    def on_state(m: State) -> None:
        got.append((f"state-{m.sender}", m.round))

    with Bus.open(client, keys, "observer", 0) as listener, Bus.open(client, keys, "learner", 1) as learner1:
        listener.subscribe(keys.state("*"), State, on_state)
        listener.subscribe(keys.round_complete("*"), RoundComplete, lambda m: got.append(("complete", m.round)))
        listener.announce()
        assert wait_until(lambda: ("observer", "0") in learner1.alive("observer"), 10)
        params = Tensor.of([1.0, 2.0], "<f4")
        learner1.publisher(keys.state(2)).put(State(run=keys.run, sender=2, round=7, params=params))  # as learner 2
        learner1.publisher(keys.state(1)).put(State(run=keys.run, sender=1, round=3, params=params))  # its own
        assert wait_until(lambda: ("state-1", 3) in set(got), 10)  # its own keys came through
    assert sorted(got) == [("state-1", 3)], "the router let learner 1 speak as learner 2 (or the observer read RoundCompletes)"


READS = [  # (reader, key it must not receive and its publisher, what it would learn, a key it may read and its publisher)
    ("lidar-0", "robots/1/scan", "world-0", "another robot's scans", "robots/0/scan", "world-0"),
    ("learner-0", "learners/2/state", "learner-2", "a State of a learner that is not its neighbour", "learners/1/state", "learner-1"),
    ("learner-0", "robots/1/samples", "lidar-1", "another robot's training points", "robots/0/samples", "lidar-0"),
    ("status-0", "learners/1/state", "learner-1", "a State (2 MB: a slow status would hold up the learners)",
     "learners/1/metrics", "learner-1"),
    # (exploring, the world reads the goals it drives to and the val_bce it logs, never a State)
    ("world-0", "learners/1/state", "learner-1", "a learner's State", "learners/1/goal", "learner-1"),
    ("learner-0", "learners/2/goal", "learner-2", "the goal of a learner that is not its neighbour", "learners/1/goal",
     "learner-1"),
]


@pytest.mark.parametrize("who, key, publisher, what, allowed, canary_from", READS, ids=[f"{r[0]}:{r[1]}" for r in READS])
@pytest.mark.integration
def test_a_member_reads_only_what_its_service_needs(run, who, key, publisher, what, allowed, canary_from):
    keys, folder, client = run
    got: list[str] = []
    with Bus.open(client, keys, *who.rsplit("-", 1)) as reader, Bus.open(client, keys, *publisher.rsplit("-", 1)) as pub, \
            Bus.open(client, keys, *canary_from.rsplit("-", 1)) as canary:
        reader.session.declare_subscriber(f"{keys.root}/**", lambda s: got.append(str(s.key_expr)[len(keys.root) + 1:]))
        sent = wait_until(lambda: (pub.session.put(f"{keys.root}/{key}", b"secret"),
                                   canary.session.put(f"{keys.root}/{allowed}", b"canary"), allowed in got)[-1], 10, 0.2)
    assert sent, f"{who} never received {allowed}, which it may read: the test proves nothing"
    assert key not in got, f"{who} could read {what} ({key})"


HOSTILE_PUTS = [  # (identity, forbidden key, what it would forge) -- by a member
    ("learner-1", "learners/2/metrics", "Metrics(final=True) as another learner"),
    ("learner-1", "robots/1/samples", "Samples(last=True) ending its own robot's data collection"),
    ("learner-1", "robots/0/scan", "a LiDAR scan in the world's name"),
    ("learner-1", "run/done", "the end of the run"),
    ("lidar-0", "robots/1/samples", "another robot's training points"),
    ("observer-0", "learners/0/state", "a State from a listener"),
]
OWN_KEY = {"learner-1": "learners/1/metrics", "lidar-0": "robots/0/samples", "observer-0": "alive/observer/0"}


@pytest.mark.parametrize("who, key, forged", HOSTILE_PUTS, ids=[f"{w}:{k}" for w, k, _ in HOSTILE_PUTS])
@pytest.mark.integration
def test_a_member_cannot_forge_what_is_not_its_own(run, who, key, forged):
    keys, folder, client = run
    got: list[str] = []
    service, ident = who.rsplit("-", 1)
    with Bus.open(client, keys, "observer", 0) as watcher, Bus.open(client, keys, "learner", 0) as learner0, \
            Bus.open(client, keys, "learner", 1) as learner1, Bus.open(client, keys, service, ident) as rogue:
        for bus in (watcher, learner0, learner1):  # between them they may read every key above
            bus.session.declare_subscriber(f"{keys.root}/**", lambda sample: got.append(str(sample.key_expr)[len(keys.root) + 1:]))
        canary = OWN_KEY[who]
        delivered = wait_until(lambda: (rogue.session.put(f"{keys.root}/{key}", b"forged"),
                                        rogue.session.put(f"{keys.root}/{canary}", b"canary"),
                                        canary in got)[-1], 10, 0.2)
    assert delivered, f"{who}'s own key {canary} never arrived: the test proves nothing"
    assert key not in got, f"{who} could forge {forged} on {key}"


@pytest.mark.integration
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


@pytest.mark.integration
def test_strangers_and_other_runs_cannot_connect(run, tmp_path):
    keys, folder, client = run
    client = client.model_copy(update={"connect_timeout_s": 2})  # each is refused at once; Zenoh retries until then
    with pytest.raises(ConfigError, match="cannot open a session"):  # no certificate at all: plain TCP
        Bus.open(client.model_copy(update={"insecure": True, "mode": "client"}), keys, "learner", 1)
    write_credentials(folder, "another-run", identities(ROBOTS), router_names(client.connect))  # the same folder
    with pytest.raises(ConfigError, match="cannot open a session"):  # another run's credentials, its own CA
        Bus.open(client, Keys("swarmmap", "another-run"), "learner", 1)


@pytest.mark.integration
def test_a_certificate_of_the_same_ca_for_another_run_gets_nothing(tmp_path, run_id):
    """Were one CA to sign for two runs, a member of the other run still could neither publish
    nor read here: the policy knows each member as ``<identity>@<run>``."""
    keys, folder, kept = Keys("swarmmap", run_id), tmp_path / "s", tmp_path / "ca"
    write_credentials(folder, run_id, identities(ROBOTS), router_names(["tcp/127.0.0.1:1"]), keep_ca=kept)
    ca = Authority.load(kept, run_id)
    key = ec.generate_private_key(ec.SECP256R1())
    other_run = Authority("another-run", ca.key, ca.cert).issue("learner-1", key.public_key())  # this CA, another run's name
    forged = tmp_path / "forged"
    write_own(own_folder(forged, "learner-1", run_id), ca.cert, other_run, pem_key(key))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    client = ZenohSettings(connect=[endpoint], multicast_scouting=False, secrets=folder, connect_timeout_s=5)
    seen, stolen = [], []
    with start_router(folder, keys, endpoint), Bus.open(client, keys, "observer", 0) as observer, \
            Bus.open(client, keys, "learner", 1) as learner1, Bus.open(client.model_copy(update={"secrets": forged}), keys,
                                                                       "learner", 1) as intruder:
        observer.session.declare_subscriber(keys.state(1), lambda s: seen.append(s.payload.to_bytes()))
        observer.session.declare_subscriber(keys.metrics(1), lambda s: seen.append(s.payload.to_bytes()))
        intruder.session.declare_subscriber(keys.metrics("*"), lambda s: stolen.append(str(s.key_expr)))
        delivered = wait_until(lambda: (intruder.session.put(keys.state(1), b"forged"), learner1.session.put(keys.state(1), b"honest"),
                                        learner1.session.put(keys.metrics(1), b"metrics"), {b"honest", b"metrics"} <= set(seen))[-1],
                               10, 0.2)
    assert delivered, "learner 1's own State and Metrics never arrived: the test proves nothing"
    assert b"forged" not in seen and stolen == [], f"another run's certificate published or read: {stolen}"


@pytest.mark.integration
def test_a_client_checks_the_routers_name(tmp_path, run_id):
    """A member's credentials cannot serve as the router: clients trust only the router's certificate."""
    keys = Keys("swarmmap", run_id)
    folder = tmp_path / "s"
    write_credentials(folder, run_id, identities(ROBOTS), router_names(["tcp/127.0.0.1:1"]))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    fake = ZenohSettings(mode="router", listen=[endpoint], multicast_scouting=False, secrets=folder)
    with Bus.open(fake, keys, "learner", 0, policy=access_policy(keys, ROBOTS)):  # learner 0 listening as a router
        with pytest.raises(ConfigError, match="cannot open a session"):
            Bus.open(ZenohSettings(connect=[endpoint], multicast_scouting=False, secrets=folder, connect_timeout_s=2),
                     keys, "learner", 1)


def test_secure_endpoints_are_tls_only(tmp_path, run_id):
    folder = tmp_path / "s"
    write_credentials(folder, run_id, identities(1), [])
    router = ZenohSettings(mode="router", multicast_scouting=True, secrets=folder)
    conf = zenoh_config(router, "router-0", run_id, policy={"enabled": True}).get_json
    assert conf("listen/endpoints") == '["tls/[::]:7447"]'  # not Zenoh's default tcp/[::]:7447
    assert conf("scouting/multicast/enabled") == "false"  # no UDP listener either
    tcp = router.model_copy(update={"listen": ["tcp/0.0.0.0:7447"]})
    assert zenoh_config(tcp, "router-0", run_id, policy={"enabled": True}).get_json("listen/endpoints") == '["tls/0.0.0.0:7447"]'
    for field, endpoint in (("listen", "udp/0.0.0.0:7447"), ("listen", "ws/0.0.0.0:7447"), ("connect", "udp/127.0.0.1:7447")):
        with pytest.raises(ConfigError, match=f"zenoh.{field}: {endpoint} is not TLS"):
            zenoh_config(router.model_copy(update={field: [endpoint]}), "router-0", run_id, policy={"enabled": True})


def port_is_free(port: int) -> bool:
    with socket.socket(socket.AF_INET6) as s:
        try:
            s.bind(("::", port))
            return True
        except OSError:
            return False


@pytest.mark.integration
def test_plain_tcp_and_udp_clients_cannot_open_a_session_with_a_router_started_without_listen(tmp_path, run_id):
    if not wait_until(lambda: port_is_free(7447), 30, 0.5):
        pytest.skip("port 7447 (Zenoh's default, which this test is about) is taken on this machine")
    keys = Keys("swarmmap", run_id)
    folder = tmp_path / "s"
    write_credentials(folder, run_id, identities(ROBOTS), router_names(["tcp/127.0.0.1:7447"]))
    with start_router(folder, keys, None, listen=[]):
        members = ZenohSettings(connect=["tcp/127.0.0.1:7447"], multicast_scouting=False, secrets=folder, connect_timeout_s=5)
        with Bus.open(members, keys, "learner", 0):  # a member reaches it on Zenoh's default port, over TLS
            pass
        with socket.create_connection(("127.0.0.1", 7447), timeout=5):  # the port is open: strangers reach a listener
            pass
        for endpoint in ("tcp/127.0.0.1:7447", "udp/127.0.0.1:7447"):
            stranger = ZenohSettings(mode="client", connect=[endpoint], multicast_scouting=False, insecure=True,
                                     connect_timeout_s=5)
            with pytest.raises(ConfigError, match="cannot open a session"):
                Bus.open(stranger, keys, "learner", 1)


def test_missing_credentials_are_named(tmp_path):
    with pytest.raises(ConfigError, match="swarmmap secrets"):
        Bus.open(ZenohSettings(connect=["tcp/127.0.0.1:1"]), Keys("swarmmap", "r"), "learner", 0)
    write_credentials(tmp_path / "s", "r", identities(2), [])
    with pytest.raises(ConfigError, match="learner-9 has no credentials of run r"):
        Bus.open(ZenohSettings(connect=["tcp/127.0.0.1:1"], secrets=tmp_path / "s"), Keys("swarmmap", "r"), "learner", 9)
    with pytest.raises(ConfigError, match="learner-0 has no credentials of run other"):  # credentials are bound to their run
        Bus.open(ZenohSettings(connect=["tcp/127.0.0.1:1"], secrets=tmp_path / "s"), Keys("swarmmap", "other"), "learner", 0)


def test_credentials_tolerate_clocks_an_hour_apart_and_a_refusal_for_time_says_so(tmp_path):
    """Certificates made on a host whose clock runs 10 min ahead are valid here; an hour and a
    half ahead, or expired, and the refusal names the clock (not a host name)."""
    import datetime

    from swarmmap.shared.wire.secrets import clock_problem

    folder = tmp_path / "s"
    write_credentials(folder, "r1", identities(1), router_names([]))
    own = own_folder(folder, "learner-0", "r1")
    now = datetime.datetime.now(datetime.timezone.utc)
    assert clock_problem(own, now - datetime.timedelta(minutes=10)) is None  # this host 10 min behind the issuer
    behind = clock_problem(own, now - datetime.timedelta(minutes=90))
    assert behind is not None and "runs about 90 min ahead" in behind and "clocks" in behind
    assert "expired" in clock_problem(own, now + datetime.timedelta(days=31))
