"""A run's credentials: its own certificate authority, a certificate per service, and the access
policy the router enforces.

``swarmmap secrets --run-dir DIR`` (and ``swarmmap up``, and the SLURM job script through
``swarmmap prepare``) writes ``DIR/secrets/``, readable by its owner alone:

- ``ca.pem``: the run's CA certificate (ECDSA P-256, valid for ``days``); ``ca.key`` its key;
- ``<identity>.pem`` / ``<identity>.key`` for every identity of the run: ``router-0``,
  ``recorder-0``, ``observer-0``, ``world-0``, ``lidar-<i>``, ``learner-<i>`` (i < robots), and
  the tools ``up-0`` and ``status-0``; the certificate's common name is the identity;
- ``acl.json5``: the Zenoh access-control policy (see :func:`access_policy`).

Every Zenoh link of the run is then mutual TLS: a process without a certificate signed by the
run's CA cannot connect at all, and the router lets each identity publish only its own keys.
"""

from __future__ import annotations

import datetime
import json
import os
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from swarmmap.shared.atomic import atomic_write_bytes
from swarmmap.shared.protocol import Keys

SINGLETONS = ("router", "recorder", "observer", "world", "up", "status")
PER_ROBOT = ("lidar", "learner")


def identity(service: str, ident: int | str) -> str:
    """The identity (certificate common name) of a service: ``learner-3``, ``world-0``."""
    return f"{service}-{ident}"


def identities(robots: int) -> list[str]:
    """Every identity of a run with ``robots`` robots."""
    return [identity(s, 0) for s in SINGLETONS] + [identity(s, i) for s in PER_ROBOT for i in range(robots)]


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "swarmmap"),
                      x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _pem_key(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())


def _write_private(path: Path, data: bytes) -> None:
    atomic_write_bytes(path, data)
    os.chmod(path, 0o600)


def _certificate(subject: str, key: ec.EllipticCurvePrivateKey, issuer: x509.Name, issuer_key: ec.EllipticCurvePrivateKey,
                 days: int, ca: bool) -> x509.Certificate:
    now = datetime.datetime.now(datetime.timezone.utc)
    builder = (x509.CertificateBuilder().subject_name(_name(subject)).issuer_name(issuer).public_key(key.public_key())
               .serial_number(x509.random_serial_number()).not_valid_before(now - datetime.timedelta(minutes=5))
               .not_valid_after(now + datetime.timedelta(days=days))
               .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True))
    if ca:
        builder = builder.add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True, content_commitment=False,
                                                      key_encipherment=False, data_encipherment=False, key_agreement=False,
                                                      encipher_only=False, decipher_only=False), critical=True)
    else:
        builder = (builder.add_extension(x509.SubjectAlternativeName([x509.DNSName(subject), x509.DNSName("localhost")]), critical=False)
                   .add_extension(x509.ExtendedKeyUsage([x509.oid.ExtendedKeyUsageOID.SERVER_AUTH,
                                                         x509.oid.ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False))
    return builder.sign(issuer_key, hashes.SHA256())


def write_secrets(folder: Path, robots: int, policy: dict, days: int = 30) -> list[str]:
    """A new CA and a certificate for every identity of the run in ``folder`` (owner-only), and
    the access policy; returns the identities. An existing CA is kept, so that services already
    running keep trusting the certificates that are added."""
    folder.mkdir(parents=True, exist_ok=True)
    os.chmod(folder, 0o700)
    if (folder / "ca.pem").exists() and (folder / "ca.key").exists():
        ca_key = serialization.load_pem_private_key((folder / "ca.key").read_bytes(), None)
        ca_cert = x509.load_pem_x509_certificate((folder / "ca.pem").read_bytes())
    else:
        ca_key = ec.generate_private_key(ec.SECP256R1())
        ca_cert = _certificate("swarmmap run CA", ca_key, _name("swarmmap run CA"), ca_key, days, ca=True)
        _write_private(folder / "ca.key", _pem_key(ca_key))
        _write_private(folder / "ca.pem", ca_cert.public_bytes(serialization.Encoding.PEM))
    names = identities(robots)
    for name in names:
        if (folder / f"{name}.pem").exists() and (folder / f"{name}.key").exists():
            continue
        key = ec.generate_private_key(ec.SECP256R1())
        cert = _certificate(name, key, ca_cert.subject, ca_key, days, ca=False)
        _write_private(folder / f"{name}.key", _pem_key(key))
        _write_private(folder / f"{name}.pem", cert.public_bytes(serialization.Encoding.PEM))
    _write_private(folder / "acl.json5", (json.dumps(policy, indent=1) + "\n").encode())
    return names


ALL_MESSAGES = ["put", "delete", "declare_subscriber", "query", "declare_queryable", "reply", "liveliness_token",
                "declare_liveliness_subscriber", "liveliness_query"]
LISTEN = ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"]


def access_policy(keys: Keys, robots: int, inproc_learner: bool = False) -> dict:
    """The router's access-control config: deny by default; every member may listen to the run
    (subscribe, query, liveliness) and receive what the router forwards; each identity may
    publish, declare tokens and answer queries only on its own keys:

    - ``learner-<i>``: ``learners/<i>/*`` and ``alive/{learner,exchange}/<i>`` (with
      ``transport: inproc``, ``learner-0`` serves every robot and holds every learner's keys);
    - ``lidar-<i>``: ``robots/<i>/samples``; ``world-0``: ``robots/*/scan``, ``world/map``
      (queryable and its replies); ``recorder-0``: ``run/done``; every service its own
      ``alive/<service>/<id>`` token.
    """
    rules: list[dict] = [
        {"id": "members-listen", "permission": "allow", "flows": ["ingress"], "messages": LISTEN, "key_exprs": [keys.everything()]},
        {"id": "members-receive", "permission": "allow", "flows": ["egress"], "messages": ALL_MESSAGES,
         "key_exprs": [keys.everything()]},
    ]
    subjects: list[dict] = []
    policies: list[dict] = []
    members = identities(robots)
    own: dict[str, list[str]] = {name: [keys.alive(*name.rsplit("-", 1))] for name in members}
    for i in range(robots):
        learner = identity("learner", 0 if inproc_learner else i)
        own[learner] += [keys.learner(i), keys.alive("learner", i), keys.alive("exchange", i)]
        own[identity("lidar", i)] += [keys.samples(i)]
    own["world-0"] += [keys.scan("*"), keys.world_map()]
    own["recorder-0"] += [keys.run_done()]
    for name in members:
        subjects.append({"id": name, "cert_common_names": [name]})
        rules.append({"id": f"{name}-speaks", "permission": "allow", "flows": ["ingress"],
                      "messages": ["put", "delete", "liveliness_token", "declare_queryable", "reply"],
                      "key_exprs": sorted(set(own[name]))})
        policies.append({"id": f"{name}-policy", "rules": ["members-listen", "members-receive", f"{name}-speaks"],
                         "subjects": [name]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}
