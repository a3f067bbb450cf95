"""A run's credentials: its own certificate authority, a key and certificate per service, each in
a folder of its own, and the access policy the router enforces.

Layout of a credentials folder (``zenoh.secrets``; ``swarmmap up`` and ``swarmmap prepare``
use ``RUN_DIR/secrets``), readable by its owner alone (0700; files 0600)::

    <identity>@<run>/ca.pem     the run's CA certificate (ECDSA P-256, valid for ``days``)
    <identity>@<run>/cert.pem   the service's certificate, signed by the run's CA
    <identity>@<run>/key.pem    the service's private key

for every identity of the run: ``router-0``, ``recorder-0``, ``observer-0``, ``world-0``,
``lidar-<i>``, ``learner-<i>`` (i < robots), the tools ``up-0`` and ``status-0``, and with a
router per host each robot host's router ``router-r<i>`` (shared/wire/mesh.py). A
certificate's common name is ``<identity>@<run>`` (:func:`cert_name`), the name the router's
access policy knows it by, so credentials are bound to their run twice over: each run has its
own CA, and a certificate of one run matches no subject of another's policy. Runs that share a
credentials folder keep apart: each has its own sub-folders.

The CA key never reaches a service. :func:`write_credentials` issues every certificate and then
discards the CA key, unless asked to keep it (``swarmmap secrets --zenoh-keep-ca DIR``, to issue
more certificates later) in a folder outside the credentials and the run directory. Compose
issues no file at all up front: each container makes its own key, and a signing step that holds
the CA key in memory signs a certificate for the identity the container claimed
(:func:`enrol`, :class:`Signer`).

Only the router's certificate names a server (the host names and addresses clients reach it
by, from ``zenoh.connect``, and the loopback ones) and may act as one (TLS server use); every
other certificate is a client's only. Every client checks the router's name when it connects.
"""

from __future__ import annotations

import datetime
import ipaddress
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from swarmmap.shared.run.atomic import atomic_write_bytes
from swarmmap.shared.wire.protocol import Keys
from swarmmap.shared.wire.services import Access, identities, policy_keys

log = logging.getLogger(__name__)

CA_FILE, CERT_FILE, KEY_FILE = "ca.pem", "cert.pem", "key.pem"
CLOCK_SKEW = datetime.timedelta(hours=1)  # certificates are valid from this long before they are issued (hosts' clocks differ)
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")


class SecretsError(Exception):
    """Credentials that cannot be written, found or trusted; the message names the folder and the fix."""


def cert_name(who: str, run: str) -> str:
    """The common name of ``who``'s certificate in run ``run``: ``learner-3@run-20250101-120000``."""
    return f"{who}@{run}"


def clock_problem(folder: Path, now: datetime.datetime | None = None) -> str | None:
    """Why the certificates in ``folder`` (a service's own) are not valid on this host's clock
    (issued by a host whose clock runs more than CLOCK_SKEW ahead, or expired), in words; None
    when they are, or cannot be read."""
    now = now or datetime.datetime.now(datetime.timezone.utc)
    for name in (CERT_FILE, CA_FILE):
        try:
            cert = x509.load_pem_x509_certificate((folder / name).read_bytes())
        except (OSError, ValueError):
            continue
        start, end = cert.not_valid_before_utc, cert.not_valid_after_utc
        if now < start:
            ahead = (start - now + CLOCK_SKEW).total_seconds() / 60
            return (f"{folder / name} is valid only from {start:%Y-%m-%d %H:%M:%S} UTC, and this host's clock says "
                    f"{now:%Y-%m-%d %H:%M:%S} UTC: the host that issued it runs about {ahead:.0f} min ahead of this one "
                    f"(more than the {CLOCK_SKEW.total_seconds() / 60:.0f} min tolerated); set the hosts' clocks right (NTP)")
        if now > end:
            return (f"{folder / name} expired at {end:%Y-%m-%d %H:%M:%S} UTC (this host's clock says {now:%Y-%m-%d %H:%M:%S} "
                    "UTC): make the run's credentials anew (swarmmap secrets), or set this host's clock right")
    return None


def own_folder(secrets: Path, who: str, run: str) -> Path:
    """The folder holding ``who``'s key, certificate and the run's CA certificate."""
    return Path(secrets) / cert_name(who, run)


def router_names(connect: list[str], extra: list[str] = ()) -> list[str]:
    """The names the router's certificate carries: the hosts of ``connect`` endpoints (how the
    clients reach it), ``extra`` and the loopback names."""
    hosts = []
    for endpoint in connect:
        address = endpoint.split("/", 1)[-1].split("#")[0].split("?")[0]
        host = address.rsplit(":", 1)[0].strip("[]")
        if host and host not in ("0.0.0.0", "::"):
            hosts.append(host)
    return list(dict.fromkeys([*hosts, *extra, *LOOPBACK_NAMES]))


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "swarmmap"),
                      x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def common_name(cert: x509.Certificate) -> str:
    """The common name of ``cert``."""
    return cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value


def _general_name(host: str) -> x509.GeneralName:
    try:
        return x509.IPAddress(ipaddress.ip_address(host))
    except ValueError:
        return x509.DNSName(host)


def pem_key(key: ec.EllipticCurvePrivateKey) -> bytes:
    """A private key as unencrypted PKCS#8 PEM (what Zenoh reads)."""
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())


def pem(cert: x509.Certificate | x509.CertificateSigningRequest) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def public_der(key: ec.EllipticCurvePublicKey) -> bytes:
    return key.public_bytes(serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo)


def private_folder(folder: Path) -> Path:
    """``folder`` made (with its parents) and readable by its owner alone."""
    folder.mkdir(parents=True, exist_ok=True)
    os.chmod(folder, 0o700)
    return folder


def write_private(path: Path, data: bytes) -> None:
    """Write ``path`` whole or not at all, readable by its owner alone from its first byte."""
    atomic_write_bytes(path, data, mode=0o600)


@dataclass
class Authority:
    """A run's certificate authority: its key, held in memory, and its certificate."""

    run: str
    key: ec.EllipticCurvePrivateKey
    cert: x509.Certificate

    @classmethod
    def new(cls, run: str, days: int = 30) -> Authority:
        key = ec.generate_private_key(ec.SECP256R1())
        now = datetime.datetime.now(datetime.timezone.utc)
        name = _name(f"swarmmap CA of run {run}")
        usage = x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True, content_commitment=False,
                              key_encipherment=False, data_encipherment=False, key_agreement=False, encipher_only=False,
                              decipher_only=False)
        cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
                .serial_number(x509.random_serial_number()).not_valid_before(now - CLOCK_SKEW)
                .not_valid_after(now + datetime.timedelta(days=days))
                .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
                .add_extension(usage, critical=True).sign(key, hashes.SHA256()))
        return cls(run, key, cert)

    @classmethod
    def load(cls, folder: Path, run: str) -> Authority | None:
        """The CA of ``run`` kept in ``folder`` (``swarmmap secrets --zenoh-keep-ca``), or None."""
        key_path, cert_path = folder / f"{run}.ca.key", folder / f"{run}.ca.pem"
        if not (key_path.is_file() and cert_path.is_file()):
            return None
        return cls(run, serialization.load_pem_private_key(key_path.read_bytes(), None),
                   x509.load_pem_x509_certificate(cert_path.read_bytes()))

    def keep(self, folder: Path) -> Path:
        """Write the CA's key and certificate into ``folder`` (owner only); returns the key's path."""
        private_folder(folder)
        write_private(folder / f"{self.run}.ca.pem", pem(self.cert))
        write_private(folder / f"{self.run}.ca.key", pem_key(self.key))
        return folder / f"{self.run}.ca.key"

    def issue(self, who: str, public_key: ec.EllipticCurvePublicKey, server_names: list[str] | None = None,
              days: int = 30) -> x509.Certificate:
        """A certificate named ``who@run`` for ``public_key``: a server's (TLS server and client
        use, for ``server_names``) when those are given, else a client's only."""
        now = datetime.datetime.now(datetime.timezone.utc)
        builder = (x509.CertificateBuilder().subject_name(_name(cert_name(who, self.run))).issuer_name(self.cert.subject)
                   .public_key(public_key).serial_number(x509.random_serial_number())
                   .not_valid_before(now - CLOCK_SKEW).not_valid_after(now + datetime.timedelta(days=days))
                   .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True))
        if server_names:
            builder = (builder.add_extension(x509.SubjectAlternativeName([_general_name(h) for h in server_names]), critical=False)
                       .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                                      critical=False))
        else:  # a client only: TLS refuses it as a server, whatever address it listens on
            builder = builder.add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
        return builder.sign(self.key, hashes.SHA256())

    def signed(self, cert: x509.Certificate) -> bool:
        """Whether ``cert`` was issued by this CA."""
        return trusted(self.cert, cert)


def trusted(ca: x509.Certificate, cert: x509.Certificate) -> bool:
    """Whether ``cert`` carries a valid signature of ``ca``."""
    try:
        cert.verify_directly_issued_by(ca)
        return True
    except Exception:  # noqa: BLE001 - InvalidSignature, another key type, another issuer: not ours
        return False


def write_own(folder: Path, ca: x509.Certificate, cert: x509.Certificate, key_pem: bytes | None) -> None:
    """``folder`` (owner only) with the CA certificate, ``cert`` and, when given, the key."""
    private_folder(folder)
    if key_pem is not None:
        write_private(folder / KEY_FILE, key_pem)
    write_private(folder / CERT_FILE, pem(cert))
    write_private(folder / CA_FILE, pem(ca))


def complete(folder: Path) -> bool:
    """Whether an identity's folder holds its key, its certificate and the CA's."""
    return all((folder / name).is_file() for name in (CA_FILE, CERT_FILE, KEY_FILE))


def write_credentials(secrets: Path, run: str, names: list[str], server_names: list[str], *,
                      keep_ca: Path | None = None, days: int = 30) -> list[str]:
    """A folder per identity of ``names`` under ``secrets`` (see the module's docstring), the
    router's certificate naming ``server_names``; returns the identities issued now.

    The CA key is discarded once the certificates are issued, unless ``keep_ca`` names a folder
    to keep it in (where a later call finds it and issues more). Identities that already have
    credentials of this run are left as they are; more of them need the kept CA."""
    secrets = Path(secrets).resolve()
    private_folder(secrets)
    missing = [n for n in names if not complete(own_folder(secrets, n, run))]
    existing = [n for n in names if n not in missing] or [p.name.rsplit("@", 1)[0] for p in secrets.glob(f"*@{run}")
                                                          if complete(p)]
    authority = Authority.load(keep_ca, run) if keep_ca is not None else None
    if existing and missing and authority is None:
        raise SecretsError(f"{secrets} holds credentials of run {run} but none for {', '.join(missing)}, and no kept CA key "
                           "of that run to issue them with (zenoh.keep_ca: the key is discarded once the certificates are "
                           "issued unless kept). Give the folder where it was kept (--zenoh-keep-ca DIR), give this run another "
                           f"id, or remove {secrets}/*@{run} to start its credentials afresh (services still running with the "
                           "old ones will be refused)")
    if not missing:
        return []
    if authority is not None and existing:
        ca_there = x509.load_pem_x509_certificate((own_folder(secrets, existing[0], run) / CA_FILE).read_bytes())
        if ca_there != authority.cert:
            raise SecretsError(f"the CA kept in {keep_ca} for run {run} did not issue the credentials in {secrets}")
    authority = authority or Authority.new(run, days)
    for name in missing:
        key = ec.generate_private_key(ec.SECP256R1())
        cert = authority.issue(name, key.public_key(), server_names if name.startswith("router-") else None, days)
        write_own(own_folder(secrets, name, run), authority.cert, cert, pem_key(key))
    if keep_ca is not None:
        kept = authority.keep(keep_ca)
        log.info("the CA key of run %s is kept in %s (owner only); no service reads it", run, kept)
    return missing


def load_own(folder: Path) -> tuple[x509.Certificate, x509.Certificate, ec.EllipticCurvePrivateKey]:
    """The CA certificate, the certificate and the key in an identity's folder."""
    ca = x509.load_pem_x509_certificate((folder / CA_FILE).read_bytes())
    cert = x509.load_pem_x509_certificate((folder / CERT_FILE).read_bytes())
    key = serialization.load_pem_private_key((folder / KEY_FILE).read_bytes(), None)
    return ca, cert, key


# ---------------------------------------------------------------- compose: enrolment and signing

REQUESTS, ISSUED = "requests", "issued"


def enrol(own: Path, who: str, run: str, signer: Path, timeout: float, poll_s: float = 0.2,
          requests: Path | None = None) -> Path:
    """Credentials for ``who`` in ``own`` (this container's folder, owner only) from the signing
    step at ``signer``: a key made here (kept: a restarted container asks with the same key),
    a certificate signing request in ``requests`` (default ``signer/requests/``), and the
    certificate the signer leaves in ``signer/issued/``, checked against its CA. Returns ``own``."""
    name = cert_name(who, run)
    requests = requests if requests is not None else signer / REQUESTS
    deadline = time.monotonic() + timeout
    ca_path = signer / CA_FILE
    while not ca_path.is_file():
        if time.monotonic() > deadline:
            raise SecretsError(f"no signer's CA certificate in {signer} after {timeout:.0f} s: is the run's start container up?")
        time.sleep(poll_s)
    ca = x509.load_pem_x509_certificate(ca_path.read_bytes())
    if complete(own):
        have_ca, cert, key = load_own(own)
        if have_ca == ca and common_name(cert) == name and public_der(cert.public_key()) == public_der(key.public_key()):
            return own  # this container's credentials of this run (a restart)
    private_folder(own)
    key_path = own / KEY_FILE
    if not key_path.is_file():
        write_private(key_path, pem_key(ec.generate_private_key(ec.SECP256R1())))
    key = serialization.load_pem_private_key(key_path.read_bytes(), None)
    csr = (x509.CertificateSigningRequestBuilder().subject_name(_name(name)).sign(key, hashes.SHA256()))
    requests.mkdir(parents=True, exist_ok=True)
    atomic_write(requests / f"{name}.csr", pem(csr))
    answer, refused = signer / ISSUED / f"{name}.pem", signer / ISSUED / f"{name}.refused"
    while time.monotonic() < deadline:
        if refused.is_file():
            raise SecretsError(f"the signer refused {name}: {refused.read_text().strip()}")
        if answer.is_file():
            cert = x509.load_pem_x509_certificate(answer.read_bytes())
            if public_der(cert.public_key()) == public_der(key.public_key()) and trusted(ca, cert):
                write_own(own, ca, cert, None)
                return own
        time.sleep(poll_s)
    raise SecretsError(f"no certificate for {name} from the signer at {signer} within {timeout:.0f} s")


def atomic_write(path: Path, data: bytes) -> None:
    """Write ``path`` whole or not at all, with the usual mode (readable by others in the folder)."""
    atomic_write_bytes(path, data, mode=0o644)


class Signer:
    """The signing step of a compose run: holds the run's CA key in memory (never on disk),
    publishes its certificate and its answers in ``folder`` (which only it writes: the services
    mount it read-only) and signs each identity's request, taken from ``requests`` (a folder the
    services write; default ``folder/requests``), once: only the identities ``names`` (those of
    the services compose runs), the first key that asks for one gets it, the same key again gets
    the same certificate (a restarted container), any other key is refused and named in the log."""

    def __init__(self, folder: Path, run: str, names: list[str], server_names: list[str], requests: Path | None = None):
        self.folder, self.run, self.server_names = folder, run, server_names
        self.requests = requests if requests is not None else folder / REQUESTS
        self.allowed = {cert_name(n, run): n for n in names}
        self.authority = Authority.new(run)
        self.issued: dict[str, bytes] = {}  # certificate name -> the public key it was issued to
        for sub in (self.requests, folder / ISSUED):
            sub.mkdir(parents=True, exist_ok=True)
            for old in sub.iterdir():  # an earlier up's requests and answers are not this run's
                old.unlink()
        atomic_write(folder / CA_FILE, pem(self.authority.cert))

    def serve_once(self) -> int:
        """Answer every request waiting; returns how many certificates were issued."""
        done = 0
        for path in sorted(self.requests.glob("*.csr")):
            name = path.name.removesuffix(".csr")
            try:
                why = self.answer(name, x509.load_pem_x509_csr(path.read_bytes()))
            except ValueError as exc:
                why = f"not a certificate signing request ({exc})"
            path.unlink(missing_ok=True)
            if why is None:
                done += 1
            else:
                log.warning("refused a certificate for %s: %s", name, why)
                atomic_write(self.folder / ISSUED / f"{name}.refused", (why + "\n").encode())
        return done

    def answer(self, name: str, csr: x509.CertificateSigningRequest) -> str | None:
        """Issue ``name``'s certificate for the key of ``csr``; returns why not, or None."""
        if name not in self.allowed:
            return f"{name} is no identity of a service of run {self.run} (the signer signs its {len(self.allowed)} services' only)"
        if not csr.is_signature_valid or common_name_of(csr) != name:
            return "the request is not signed by its key, or names another identity"
        key = public_der(csr.public_key())
        if self.issued.setdefault(name, key) != key:
            return f"{name} was already issued to another key in this run (another container claims it?)"
        who = self.allowed[name]
        cert = self.authority.issue(who, csr.public_key(), self.server_names if who.startswith("router-") else None)
        atomic_write(self.folder / ISSUED / f"{name}.pem", pem(cert))
        log.info("issued %s", name)
        return None


def common_name_of(csr: x509.CertificateSigningRequest) -> str | None:
    names = csr.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    return names[0].value if names else None


# ---------------------------------------------------------------- the router's access policy

ALL_MESSAGES = ["put", "delete", "declare_subscriber", "query", "declare_queryable", "reply", "liveliness_token",
                "declare_liveliness_subscriber", "liveliness_query"]
LISTEN = ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"]
SPEAK = ["put", "delete", "liveliness_token", "declare_queryable", "reply"]
DELIVER = ["put", "delete", "reply"]  # what carries data to a member: only on the keys it may read
DECLARATIONS = ["declare_subscriber", "declare_queryable", "liveliness_token", "declare_liveliness_subscriber",
                "liveliness_query"]


def access_policy(keys: Keys, robots: int, inproc_learner: bool = False,
                  neighbours: dict[int, set[int]] | None = None, host_routers: bool = False) -> dict:
    """The router's access-control config: deny by default; each identity (by its certificate
    name, bound to this run) may publish, declare tokens and answer queries only on its own keys
    (its kind's declaration, :mod:`swarmmap.shared.wire.services`), and receive data and replies only on
    what its service reads, whatever it subscribes to. Declarations pass to every member, so that
    publishers learn of their subscribers. With ``host_routers`` (a router per host), the
    other routers of the run relay everything under the run to and from this one: each router
    holds its own clients to these rules, so a member's messages are checked where it joins."""
    rules: list[dict] = [
        {"id": "declarations", "permission": "allow", "flows": ["egress"], "messages": DECLARATIONS, "key_exprs": [keys.everything()]},
        # Any member may declare subscriptions and queries under the run (a wildcard one too); what
        # reaches it is filtered on the way out, by the keys it may read.
        {"id": "listens", "permission": "allow", "flows": ["ingress"], "messages": LISTEN, "key_exprs": [keys.everything()]},
    ]
    subjects: list[dict] = []
    policies: list[dict] = []
    own, readable = policy_keys(keys, Access(robots, neighbours, inproc_learner, host_routers))
    if host_routers:
        rules.append({"id": "relays", "permission": "allow", "flows": ["ingress", "egress"], "messages": ALL_MESSAGES,
                      "key_exprs": [keys.everything()]})
    for name in identities(robots, host_routers):
        subjects.append({"id": name, "cert_common_names": [cert_name(name, keys.run)]})
        if host_routers and name.startswith("router-"):
            policies.append({"id": f"{name}-policy", "subjects": [name], "rules": ["relays"]})
            continue
        rules += [
            {"id": f"{name}-speaks", "permission": "allow", "flows": ["ingress"], "messages": SPEAK, "key_exprs": own[name]},
            {"id": f"{name}-is-asked", "permission": "allow", "flows": ["egress"], "messages": ["query"], "key_exprs": own[name]},
            {"id": f"{name}-receives", "permission": "allow", "flows": ["egress"], "messages": DELIVER,
             "key_exprs": readable[name]},
        ]
        policies.append({"id": f"{name}-policy", "subjects": [name],
                         "rules": ["declarations", "listens", *(f"{name}-{verb}" for verb in ("speaks", "is-asked", "receives"))]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}
