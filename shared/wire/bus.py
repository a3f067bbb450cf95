"""One Zenoh session per service: typed publishing, validated subscriptions, liveliness.

Usage::

    with Bus.open(cfg.zenoh, Keys(cfg.key_prefix, cfg.run_id), "learner", 3) as bus:
        pub = bus.publisher(bus.keys.state(3))
        bus.subscribe(bus.keys.state("*"), State, on_state)
        pub.put(State(run=..., sender=3, round=0, params=Tensor.of(theta)))

Every refused payload is dropped with one log line per (key, reason) and counted in
``bus.dropped``; the service keeps running. A key whose payloads are refused again and again
(REFUSALS_TO_MUTE within REFUSAL_WINDOW_S: a hostile member's flood) is muted: its payloads are
dropped unread (counted as ``muted``) for MUTE_S seconds, then twice as long each time it starts
again. Data publishers are reliable and block rather
than drop when a receiver is slow, so no training point or State is lost to congestion.
"""

from __future__ import annotations

import collections
import json
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import zenoh

from swarmmap.shared.run import runtime
from swarmmap.shared.run.config import ConfigError, ZenohSettings
from swarmmap.shared.run.runtime import Stopped
from swarmmap.shared.wire.codec import decode, encode
from swarmmap.shared.wire.protocol import DEFAULT_MAX_MESSAGE_BYTES, Keys, Message, ProtocolError, RunDone, Tensor, WorldMap
from swarmmap.shared.wire.secrets import CA_FILE, CERT_FILE, KEY_FILE, SecretsError, clock_problem, enrol, own_folder
from swarmmap.shared.wire.services import identity
from swarmmap.shared.world.sensing import draw_validation

log = logging.getLogger(__name__)
M = TypeVar("M", bound=Message)
DEFAULT_ROUTER_LISTEN = "tls/[::]:7447"  # Zenoh's default port, TLS only
# How long a session waits on a link it cannot send on (a receiver that stopped reading) before
# it closes that link (Zenoh's default: 5 s for both). The router gives up on a stuck member
# first, long before a publisher would give up on its own link to the router, which would lose
# what it sends meanwhile to every receiver (bench/slow_subscriber.py).
ROUTER_CLOSES_STUCK_S, CLIENT_CLOSES_STUCK_S = 2.0, 60.0
# A router linked to other routers (one per host) waits longer: a 1 Mbit/s link holding a burst
# (the world's scans at time_scale 0) takes more than 2 s to take the next batch, and closing it
# loses what was queued (zenoh.stuck_s; bench/links.py).
LINKED_ROUTER_CLOSES_STUCK_S = 30.0
REFUSALS_TO_MUTE, REFUSAL_WINDOW_S, MUTE_S = 20, 10.0, 10.0


def zenoh_config(settings: ZenohSettings, who: str, run: str = "", policy: dict | None = None) -> zenoh.Config:
    """A zenoh.Config for identity ``who`` (``learner-3``) of run ``run``: the JSON5 file first,
    then each field that is set, then the run's security (see :func:`secure`) unless ``insecure``;
    a router enforces ``policy`` (its access control)."""
    conf = zenoh.Config.from_file(str(settings.config_file)) if settings.config_file else zenoh.Config()
    mode, connect, listen, scouting = settings.mode, settings.connect, settings.listen, settings.multicast_scouting
    if not settings.insecure:
        mode, connect, listen = secure(conf, settings, who, run, policy)
        scouting = False  # a secure client finds its router by zenoh.connect; no UDP listener is opened
    if mode is not None:
        conf.insert_json5("mode", json.dumps(mode))
    # secure: the endpoints are exactly these, whatever the config file says
    if connect or not settings.insecure:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
    if listen or not settings.insecure:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    if scouting is not None:
        conf.insert_json5("scouting/multicast/enabled", json.dumps(scouting))
    if settings.shared_memory is not None:
        conf.insert_json5("transport/shared_memory/enabled", json.dumps(settings.shared_memory))
    stuck_s = settings.stuck_s or (ROUTER_CLOSES_STUCK_S if mode == "router" else CLIENT_CLOSES_STUCK_S)
    conf.insert_json5("transport/link/tx/queue/congestion_control/block/wait_before_close", json.dumps(int(stuck_s * 1e6)))
    return conf


def tls_only(endpoints: list[str], field: str) -> list[str]:
    """``endpoints`` as a secure session uses them: ``tls/`` as given, ``tcp/`` served as
    ``tls/`` (said once in the log); any other protocol (``udp/``, ``ws/``, ...) raises
    ConfigError naming ``field``."""
    out = []
    for endpoint in endpoints:
        protocol, _, rest = endpoint.partition("/")
        if protocol == "tls":
            out.append(endpoint)
        elif protocol == "tcp":
            log.info("%s: %s is served as tls/%s (a secure run speaks TLS only)", field, endpoint, rest)
            out.append(f"tls/{rest}")
        else:
            raise ConfigError(f"config error:\n  {field}: {endpoint} is not TLS; a secure run speaks TLS only: give tls/{rest} "
                              f"(tcp/ is served as tls/), or opt out with --zenoh-insecure")
    return out


def credentials(settings: ZenohSettings, who: str, run: str) -> Path:
    """``who``'s own credentials folder in ``settings.secrets``; with ``settings.signer``
    (compose) they are made there first (:func:`~swarmmap.shared.wire.secrets.enrol`)."""
    if settings.secrets is None:
        raise ConfigError("config error:\n  zenoh.secrets: no credentials for this run. Create them with `swarmmap secrets "
                          "--run-dir RUN_DIR` (swarmmap up does it) or opt out with --zenoh-insecure")
    folder = own_folder(settings.secrets, who, run)
    if settings.signer is not None:
        try:
            return enrol(folder, who, run, settings.signer, settings.connect_timeout_s, requests=settings.signer_requests)
        except (SecretsError, OSError) as exc:
            raise ConfigError(f"config error:\n  zenoh.signer: {who} got no certificate: {exc}") from None
    missing = [str(folder / name) for name in (CA_FILE, CERT_FILE, KEY_FILE) if not (folder / name).is_file()]
    if missing:
        raise ConfigError(f"config error:\n  zenoh.secrets: {who} has no credentials of run {run} in {settings.secrets} "
                          f"(missing {', '.join(missing)}); create them with `swarmmap secrets --run-dir RUN_DIR`")
    return folder


def secure(conf: zenoh.Config, settings: ZenohSettings, who: str, run: str, policy: dict | None) -> tuple[str, list[str], list[str]]:
    """Mutual TLS with ``who``'s own key and certificate (:func:`credentials`), every client
    checking the router's certificate name; the router also enforces ``policy``. Every other
    session is a client of the router, so that every message passes the policy, and none
    listens. Every endpoint is TLS (:func:`tls_only`); a router given none listens on
    ``tls/[::]:7447``. Returns mode, connect, listen."""
    folder = credentials(settings, who, run)
    router = settings.mode == "router"
    tls = {"root_ca_certificate": str(folder / CA_FILE), "enable_mtls": True, "verify_name_on_connect": True,
           "connect_private_key": str(folder / KEY_FILE), "connect_certificate": str(folder / CERT_FILE)}
    if router:
        if policy is None:
            raise ConfigError(f"config error:\n  zenoh.mode: {who} cannot be a secure router: no access policy for run {run}")
        tls |= {"listen_private_key": str(folder / KEY_FILE), "listen_certificate": str(folder / CERT_FILE)}
        conf.insert_json5("access_control", json.dumps(policy))
    for field, value in tls.items():
        conf.insert_json5(f"transport/link/tls/{field}", json.dumps(value))
    connect = tls_only(settings.connect, "zenoh.connect")
    if not router:
        if not connect:
            raise ConfigError(f"config error:\n  zenoh.connect: {who} needs the router's endpoint (tls/HOST:PORT) in a secure "
                              "run (no multicast scouting)")
        # start in any order: wait for the router
        conf.insert_json5("connect/timeout_ms", json.dumps({"router": -1, "peer": -1, "client": int(settings.connect_timeout_s * 1000)}))
        return "client", connect, []
    return "router", connect, tls_only(settings.listen, "zenoh.listen") or [DEFAULT_ROUTER_LISTEN]


class RateCounter:
    """Counts bytes per key; thread-safe."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.bytes: collections.Counter[str] = collections.Counter()

    def add(self, key: str, size: int) -> None:
        with self._lock:
            self.bytes[key] += size

    def bytes_where(self, keep: Callable[[str], bool]) -> int:
        """Bytes counted on the keys for which ``keep(key)`` is true."""
        with self._lock:
            return sum(n for k, n in self.bytes.items() if keep(k))


class Publisher:
    """A declared publisher that encodes messages and counts what it sends."""

    def __init__(self, bus: Bus, key: str):
        self.key = key
        self._bus = bus
        self._pub = bus.session.declare_publisher(
            key, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE)

    def put(self, message: Message) -> int:
        """Send ``message``; returns its size in bytes."""
        return self.put_bytes(encode(message))

    def put_bytes(self, payload: bytes | bytearray) -> int:
        """Send an already encoded message."""
        self._pub.put(payload)
        self._bus.sent.add(self.key, len(payload))
        return len(payload)

    def matched(self) -> bool:
        """Whether this session knows of a subscriber to the key (Zenoh sends nothing where it knows none)."""
        status = self._pub.matching_status
        return bool(getattr(status, "matching", status))

    def undeclare(self) -> None:
        self._pub.undeclare()


def _open_session(conf: zenoh.Config, stop: threading.Event | None) -> zenoh.Session:
    """``zenoh.open(conf)``; with ``stop``, in a thread of its own, given up (:class:`Stopped`) once
    ``stop`` is set (the session, if it opens later, is closed by that thread)."""
    if stop is None:
        return zenoh.open(conf)
    out: dict[str, Any] = {}
    done = threading.Event()

    def opener() -> None:
        try:
            out["session"] = zenoh.open(conf)
        except BaseException as exc:  # re-raised in the caller's thread
            out["error"] = exc
        done.set()
        if stop.is_set() and "session" in out:
            out["session"].close()

    threading.Thread(target=opener, name="zenoh open", daemon=True).start()
    while not done.wait(0.1):
        if stop.is_set():
            raise Stopped
    if "error" in out:
        raise out["error"]
    if stop.is_set():
        raise Stopped
    return out["session"]


class Bus:
    """A service's Zenoh session with the run's keys, counters and its liveliness token."""

    def __init__(self, session: zenoh.Session, keys: Keys, service: str, ident: int | str,
                 max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES):
        self.session = session
        self.keys = keys
        self.service = service
        self.ident = ident
        self.max_message_bytes = max_message_bytes
        self.sent = RateCounter()
        self.received = RateCounter()
        self.dropped: collections.Counter[str] = collections.Counter()
        self.dropped_on: collections.Counter[str] = collections.Counter()  # the same, per key (whose sender it names)
        self._logged: set[tuple[str, str]] = set()
        self._refusals: dict[str, collections.deque[float]] = collections.defaultdict(
            lambda: collections.deque(maxlen=REFUSALS_TO_MUTE))
        self._muted: dict[str, tuple[float, float]] = {}  # key -> (muted until, the next mute's length)
        self._handles: list[Any] = []
        self._tokens: dict[str, Any] = {}
        self.run_done: RunDone | None = None

    @classmethod
    def open(cls, settings: ZenohSettings, keys: Keys, service: str, ident: int | str = 0, policy: dict | None = None,
             stop: threading.Event | None = None) -> Bus:
        """Open a Zenoh session for ``service`` ``ident`` of the run named by ``keys``; a
        secure router enforces ``policy`` (its access control).

        A config file Zenoh cannot read, an endpoint it cannot use or a router it cannot reach
        (or whose certificate is not this run's router's) raises ConfigError; ``stop`` (by default
        the process's shutdown event, :func:`~swarmmap.shared.run.runtime.shutdown_event`) set while
        the session opens (a router that went away makes it wait for its connect timeout) raises
        :class:`Stopped` at once."""
        who = identity(service, ident)
        if settings.insecure:
            log.warning("INSECURE: %s opens its Zenoh session without TLS, authentication or access control; "
                        "anyone who reaches the router can join this run and poison it", who)
        try:
            session = _open_session(zenoh_config(settings, who, keys.run, policy), stop or runtime.SHUTDOWN)
        except zenoh.ZError as exc:
            given = settings.model_dump(exclude_defaults=True, mode="json")
            hint = "" if settings.insecure or settings.mode == "router" else (
                f" (a secure client trusts only run {keys.run}'s router, by its certificate: the endpoint's host must be "
                "one it names, the hosts of zenoh.connect when the credentials were made)")
            clock = None if settings.insecure or settings.secrets is None else clock_problem(
                own_folder(settings.secrets, who, keys.run))
            hint = f" ({clock})" if clock is not None else hint
            raise ConfigError(f"config error:\n  zenoh: cannot open a session with {given or 'the defaults'}: "
                              f"{str(exc).split(' at /')[0]}{hint}") from None
        return cls(session, keys, service, ident)

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- liveliness

    def announce(self, ident: int | str | None = None, service: str | None = None) -> None:
        """Declare this service's liveliness token ``alive/<service>/<ident>`` (defaults: this
        bus's own; a process serving several robots announces each). Do it after the
        subscribers are declared, so whoever sees the token can already reach them."""
        key = self.keys.alive(service or self.service, str(self.ident if ident is None else ident))
        if key not in self._tokens:
            self._tokens[key] = self.session.liveliness().declare_token(key)

    def alive(self, service: str = "*") -> set[tuple[str, str]]:
        """(service, id) of every live token of this run, optionally of one service."""
        out = set()
        for reply in self.session.liveliness().get(self.keys.alive(service), timeout=2.0):
            if reply.ok is not None:
                out.add(self.keys.parse_alive(str(reply.ok.key_expr)))
        return out

    def watch_alive(self, service: str, on_change: Callable[[str, bool], None]) -> None:
        """Call ``on_change(id, alive)`` for every token of ``service``, past and future."""

        def handler(sample: zenoh.Sample) -> None:
            _, ident = self.keys.parse_alive(str(sample.key_expr))
            on_change(ident, sample.kind == zenoh.SampleKind.PUT)

        self._handles.append(
            self.session.liveliness().declare_subscriber(self.keys.alive(service), handler, history=True))

    def wait_alive(self, service: str, idents: set[str], timeout: float,
                   stop: threading.Event | None = None) -> set[str]:
        """Wait until every id in ``idents`` of ``service`` has a token; return those missing."""
        deadline = time.monotonic() + timeout
        missing = set(idents)
        while True:
            missing = set(idents) - {i for s, i in self.alive(service)}
            if not missing or time.monotonic() >= deadline or (stop is not None and stop.is_set()):
                return missing
            time.sleep(0.1) if stop is None else stop.wait(0.1)

    @staticmethod
    def wait_matched(pubs: list[Publisher], timeout: float, stop: threading.Event) -> list[Publisher]:
        """Wait until each of ``pubs`` has a subscriber this session knows of; return those without.

        A consumer's liveliness token can reach this session before its subscription does (they
        travel apart), and what a publisher sends before it knows a subscriber is dropped: a
        burst sent right after the token (a replay, a log served as fast as it is taken) would be
        lost, so the sender waits for both."""
        deadline = time.monotonic() + timeout
        while True:
            waiting = [p for p in pubs if not p.matched()]
            if not waiting or time.monotonic() >= deadline or stop.is_set():
                return waiting
            stop.wait(0.05)

    def end_with_run(self, stop: threading.Event) -> None:
        """Set ``stop`` when the run's recorder says the run is over (``RunDone``, kept in
        ``self.run_done``): every service ends by itself, whoever launched it."""

        def on_done(msg: RunDone) -> None:
            if self.run_done is None:
                log.info("the run is over (%s): %s", "ok" if msg.ok else "failed", msg.reason)
            self.run_done = msg
            stop.set()

        self.subscribe(self.keys.run_done(), RunDone, on_done, sender_from_key=False)

    # -- data

    def publisher(self, key: str) -> Publisher:
        pub = Publisher(self, key)
        self._handles.append(pub)
        return pub

    def refuse(self, key: str, err: ProtocolError) -> None:
        """Count a refused payload; log the first of each (key, reason); mute a key that floods."""
        self.dropped[err.reason] += 1
        self.dropped_on[key] += 1
        if (key, err.reason) not in self._logged:
            self._logged.add((key, err.reason))
            log.warning("dropped a message on %s (%s); further ones like it are only counted", key, err)
        now = time.monotonic()
        times = self._refusals[key]
        times.append(now)
        if len(times) == REFUSALS_TO_MUTE and now - times[0] <= REFUSAL_WINDOW_S:
            times.clear()
            length = self._muted.get(key, (0.0, MUTE_S))[1]
            self._muted[key] = (now + length, 2 * length)
            log.warning("%d messages refused on %s within %.0f s: its further messages are dropped unread for %.0f s",
                        REFUSALS_TO_MUTE, key, REFUSAL_WINDOW_S, length)

    def muted(self, key: str) -> bool:
        """Whether ``key``'s payloads are dropped unread now (it flooded this bus with refused ones)."""
        until = self._muted.get(key)
        return until is not None and time.monotonic() < until[0]

    def subscribe(self, key_expr: str, model: type[M], callback: Callable[[M], None], *,
                  sender_from_key: bool = True, check: Callable[[M], None] | None = None, newest: int = 0,
                  direct: bool = False, max_bytes: int | None = None) -> None:
        """Call ``callback(message)`` for every valid ``model`` published on ``key_expr``.

        With ``sender_from_key`` the id in the key (``robots/<id>/``, ``learners/<id>/``) must
        equal the message's sender. ``check`` may raise ProtocolError to refuse more.

        A callback runs on Zenoh's receiving thread and must be quick: while it runs, nothing
        more is read from the router, which then holds up the publishers (their congestion
        control blocks so that no message is lost). A watcher that need not see every message
        (the observer, ``up``'s progress) passes ``newest=N``: messages then wait in a ring of
        the N newest (the oldest dropped) and a thread of its
        own runs the callback, so that a slow callback never slows a publisher
        (bench/slow_subscriber.py). ``direct`` runs the callback in Zenoh's receiving thread itself:
        a callback that blocks then holds back the publishers (their back pressure) on purpose (a
        lidar streamer whose inbox is full holds back the world's scans). ``max_bytes``: a tighter
        limit than the bus's for these messages (a learner's: a small multiple of its own State).
        """
        limit = self.max_message_bytes if max_bytes is None else min(max_bytes, self.max_message_bytes)

        def handler(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            if self._muted and self.muted(key):
                self.dropped["muted"] += 1
                self.dropped_on[key] += 1
                return
            payload = sample.payload.to_bytes()
            self.received.add(key, len(payload))
            try:
                sender = self.keys.ident_of(key) if sender_from_key else None
                msg = decode(payload, model, run=self.keys.run, sender=sender, max_bytes=limit)
                if check is not None:
                    check(msg)
            except ProtocolError as err:
                self.refuse(key, err)
                return
            try:
                callback(msg)
            except Exception:  # a bug in a handler must not kill Zenoh's thread silently
                log.exception("handler for %s failed", key)

        if newest <= 0:
            self._handles.append(self.session.declare_subscriber(key_expr, zenoh.handlers.Callback(handler, indirect=not direct)))
            return
        sub = self.session.declare_subscriber(key_expr, zenoh.handlers.RingChannel(newest))
        self._handles.append(sub)
        threading.Thread(target=self._drain, args=(sub, handler), name=f"sub {key_expr}", daemon=True).start()

    @staticmethod
    def _drain(sub: Any, handler: Callable[[zenoh.Sample], None]) -> None:
        """Run ``handler`` on every sample of a ring subscriber until it is undeclared."""
        try:
            for sample in sub:
                handler(sample)
        except zenoh.ZError:  # the subscriber was undeclared (the bus closed)
            pass

    def serve(self, key: str, reply: Callable[[str], bytes]) -> None:
        """Answer every query on ``key`` with ``reply(parameters)`` (the query's selector
        parameters, "" when it has none)."""

        def handler(query: zenoh.Query) -> None:
            try:
                payload = reply(str(query.parameters))
            except Exception as exc:
                log.exception("query on %s failed", key)
                query.reply_err(str(exc).encode())
                return
            query.reply(key, payload)
            self.sent.add(key, len(payload))

        self._handles.append(self.session.declare_queryable(key, handler))

    def query(self, key: str, model: type[M], timeout: float,
              stop: threading.Event | None = None, retry_every: float = 0.5) -> M | None:
        """Query ``key`` until a valid ``model`` reply comes or ``timeout`` passes. A query that
        nobody answers yet ends at once and is asked again; one that is answered waits for its reply
        as long as ``timeout`` allows (a large reply over a slow link: asking again would send it
        once more, on a link it already fills)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not (stop is not None and stop.is_set()):
            for reply in self._replies(key, max(0.5, deadline - time.monotonic()), stop):
                if reply.ok is None:
                    continue
                payload = reply.ok.payload.to_bytes()
                self.received.add(key, len(payload))
                try:
                    return decode(payload, model, run=self.keys.run, max_bytes=self.max_message_bytes)
                except ProtocolError as err:
                    self.refuse(key, err)
            time.sleep(retry_every) if stop is None else stop.wait(retry_every)
        return None

    def _replies(self, key: str, timeout: float, stop: threading.Event | None):
        """The replies to a query on ``key`` as they come, until every one came, ``timeout``
        passed, or ``stop`` was set (a service stopped while it waits for a reply stops at once)."""
        replies = self.session.get(key, timeout=timeout)
        while True:
            try:
                reply = replies.try_recv()
            except zenoh.ZError:  # closed: every reply came, or the query timed out
                return
            if reply is not None:
                yield reply
            elif stop is not None and stop.is_set():
                return
            else:
                time.sleep(0.02)

    def world(self, timeout: float, stop: threading.Event | None = None) -> WorldMap | None:
        """The world's map (:meth:`query`); None, logged unless ``stop`` is set, when no reply comes
        within ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        world = self.query(self.keys.world_map(), WorldMap, timeout, stop)
        if world is not None and world.validation is not None:
            try:
                points, labels, differs = draw_validation(world)
            except ValueError as exc:  # a grid the recipe cannot be drawn on (no free cell, say)
                points = labels = None
                differs = f"it cannot be drawn: {exc}"
            if differs is not None:  # another numpy, say: the world's own points, then
                log.warning("%s-%s: the validation set drawn here from the world's grid differs from the world's "
                            "(%s); asking the world for its points", self.service, self.ident, differs)
                world = self.query(f"{self.keys.world_map()}?points", WorldMap, max(1.0, deadline - time.monotonic()),
                                   stop)
                if world is not None and world.val_points is None:
                    log.error("%s-%s: the world sent no validation points when asked for them", self.service, self.ident)
                    return None
            elif points is not None and labels is not None:
                world = world.model_copy(update={"val_points": Tensor.of(points, "<f4"),
                                                 "val_labels": Tensor.of(labels, "<f4"), "validation": None})
        if world is None and not (stop is not None and stop.is_set()):
            log.error("%s-%s: no reply from the world on %s within %.0f s", self.service, self.ident,
                      self.keys.world_map(), timeout)
        return world

    def close(self) -> None:
        if self.dropped:  # what this service refused, in its log for good
            log.warning("%s-%s refused %d message(s): %s", self.service, self.ident, sum(self.dropped.values()),
                        ", ".join(f"{n} {reason}" for reason, n in sorted(self.dropped.items())))
        for handle in reversed(self._handles):
            try:
                handle.undeclare()
            except Exception:
                pass
        self._handles.clear()
        for token in self._tokens.values():
            try:
                token.undeclare()
            except Exception:
                pass
        self._tokens.clear()
        self.session.close()

