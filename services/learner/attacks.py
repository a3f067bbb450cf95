"""A hostile member of the run, for tests, the bench and researchers (``faults.attack``).

A learner listed in ``faults.attackers`` runs with its own credentials and trains as any other,
but what it tells its neighbours is a lie (:class:`HostileTransport` rewrites each State it sends,
after its own update has used the honest one). The attacks, with theta the attacker's honest
parameters of the round (a tracker or counts after them are sent as they are):

- ``ratchet``: theta + 0.45 ||theta|| u, u a random direction drawn anew each round (within the
  plain norm check's 0.5, re-anchored on the attacker's parameters every round);
- ``signflip``: the output layer's weights and bias negated;
- ``scale``: 1.45 theta;
- ``noise``: theta plus Gaussian noise of 0.05 ||theta|| in all (about the honest spread);
- ``sigma``: a Bayesian network's rho lowered by 2 (false certainty: sigma about e^-2 x its own)
  and its means moved by 0.3 of their norm in a random direction;
- ``stall``: RoundCompletes, but never a State;
- ``equivocate``: two States for every round, the honest one and a ratchet's;
- ``far-future``: its honest State, but as the State of three rounds ahead, never a RoundComplete;
- ``repeat``: its first State again and again, never a RoundComplete;
- ``bomb``: object bombs (a valid header, then a million empty maps in 1 MB) instead of its States
  and RoundCompletes, and twice a 63 MB one of 16 million;
- ``metrics-flood``: honest States, and for two seconds Metrics of a new round as fast as it can.

Each is a plug-in (an :class:`~swarmmap.shared.plugins.AttackPlugin` named in the entry-point group
``swarmmap.attacks``); another package adds its own the same way.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import msgpack
import numpy as np

from swarmmap.services.learner.transport import Envelope, Transport, plain_vector
from swarmmap.shared.learning.bnn import is_rho
from swarmmap.shared.learning.layout import StateLayout
from swarmmap.shared.plugins import AttackPlugin, load
from swarmmap.shared.wire.protocol import Metrics

log = logging.getLogger("learner")


def output_layer(layout: StateLayout) -> np.ndarray:
    """Where the output layer (the last layer's weight and bias) lies in the parameters."""
    layers = sorted({name.rsplit(".", 1)[0] for name, _, _ in layout.tensors}, key=lambda n: [int(p) if p.isdigit() else p
                                                                                               for p in n.split(".")])
    last = layers[-1]
    return np.concatenate([np.arange(at, at + n) for name, at, n in layout.tensors if name.rsplit(".", 1)[0] == last])


class Liar:
    """What an attacker sends instead of its State ``v`` (its parameters first, as ``layout`` says),
    by the attack plug-in called ``attack`` (``faults.attack``)."""

    def __init__(self, attack: str, layout: StateLayout, seed: int):
        self.attack, self.layout = attack, layout
        self.plugin = load("attacks", attack)
        self.rng = np.random.default_rng([seed, 4242])
        self.rho = np.zeros(layout.param_count, bool)
        for name, at, n in layout.tensors:
            self.rho[at : at + n] = is_rho(name)
        self.out = output_layer(layout)

    def direction(self, n: int) -> np.ndarray:
        """A random unit vector of ``n`` values (drawn from the attacker's seeded generator)."""
        u = self.rng.standard_normal(n)
        return u / max(float(np.linalg.norm(u)), 1e-12)

    def lie(self, v: np.ndarray) -> np.ndarray:
        out = np.array(v, dtype=np.float32, copy=True)
        if self.plugin.lie is not None:
            self.plugin.lie(self, out[: self.layout.param_count])  # a view: the attacks write the parameters only
        return out


# ----------------------------------------------------------------- swarmmap's own attacks (plug-ins)


def _ratchet(liar: Liar, theta: np.ndarray) -> None:
    theta += (0.45 * float(np.linalg.norm(theta)) * liar.direction(theta.size)).astype(np.float32)


def _signflip(liar: Liar, theta: np.ndarray) -> None:
    theta[liar.out] *= -1


def _scale(liar: Liar, theta: np.ndarray) -> None:
    theta *= 1.45


def _noise(liar: Liar, theta: np.ndarray) -> None:
    norm = float(np.linalg.norm(theta))
    theta += (0.05 * norm / np.sqrt(theta.size) * liar.rng.standard_normal(theta.size)).astype(np.float32)


def _sigma(liar: Liar, theta: np.ndarray) -> None:
    means = ~liar.rho
    theta[liar.rho] -= 2.0
    theta[means] += (0.3 * float(np.linalg.norm(theta[means])) * liar.direction(int(means.sum()))).astype(np.float32)


RATCHET = AttackPlugin(_ratchet, "a random direction at 0.45 of the norm, anew each round")
SIGNFLIP = AttackPlugin(_signflip, "the output layer negated")
SCALE = AttackPlugin(_scale, "the parameters x 1.45")
NOISE = AttackPlugin(_noise, "Gaussian noise of 0.05 of the norm in all")
SIGMA = AttackPlugin(_sigma, "false certainty: a Bayesian network's rho lowered by 2, its means moved", models=("bnn",))
STALL = AttackPlugin(None, "RoundCompletes, never a State", sends="nothing")
EQUIVOCATE = AttackPlugin(_ratchet, "two States a round: the honest one and a ratchet's", sends="both")
FAR_FUTURE = AttackPlugin(None, "its State as one of three rounds ahead, never a RoundComplete", sends="ahead")
REPEAT = AttackPlugin(None, "its first State again and again, never a RoundComplete", sends="repeat")
BOMB = AttackPlugin(None, "object bombs (millions of tiny maps under a valid header) instead of its messages", sends="bomb")
METRICS_FLOOD = AttackPlugin(None, "honest States; Metrics of a new round as fast as it can for 2 s", sends="metrics")
BIG_BOMBS = 2  # the 63 MB bombs a bomb attacker sends (on its RoundComplete key), besides a 1 MB one for each message


def bomb_payload(run: str, sender: int, kind: str, maps: int) -> bytes:
    """A message of ``kind`` with a valid header whose next field is an array of ``maps`` empty maps."""
    head = msgpack.packb({"v": 2, "kind": kind, "run": run, "sender": sender, "round": 0})
    return b"\xde\x00\x06" + head[1:] + msgpack.packb("params") + b"\xdd" + maps.to_bytes(4, "big") + b"\x80" * maps


def flood_metrics(publish: Callable[[Metrics], object], run: str, robot: int, seconds: float = 2.0) -> None:
    """The metrics-flood attack: Metrics of a new round each, as fast as ``publish`` takes them,
    for ``seconds`` (a thread of its own), with the wall time in them."""

    def flood() -> None:
        t0 = time.monotonic()
        k = 0
        while time.monotonic() - t0 < seconds:
            publish(Metrics(run=run, sender=robot, round=k, wall_time_s=time.monotonic() - t0, val_bce=0.0,
                            consensus_error=0.0, bytes_sent=0, bytes_received=0))
            k += 1
        log.warning("node %d: HOSTILE: sent Metrics of %d rounds in %.0f s", robot, k, seconds)

    threading.Thread(target=flood, name="metrics flood", daemon=True).start()


def raw_link(transport):
    """The link under ``transport`` that sends raw payloads (``send_raw``), or None."""
    while transport is not None and not hasattr(transport, "send_raw"):
        transport = getattr(transport, "inner", None)
    return transport


class HostileTransport:
    """A transport whose sender lies (:class:`Liar`) or stalls; what it receives is untouched."""

    def __init__(self, inner: Transport, node: int, attack: str, layout: StateLayout, seed: int):
        self.inner, self.node, self.attack = inner, node, attack
        self.liar = Liar(attack, layout, seed)
        self.lies: dict[int, np.ndarray] = {}  # one lie a round: a resend says the same again
        self.first: tuple[int, np.ndarray] | None = None  # repeat: the State it says again and again
        self.link = raw_link(inner)
        self.bombs: dict[str, bytes] = {}
        self.big_bombs = BIG_BOMBS
        if self.liar.plugin.sends == "bomb" and self.link is None:
            raise ValueError(f"faults.attack {attack}: this link cannot send raw payloads")
        log.warning("node %d: HOSTILE: it attacks its neighbours (%s): faults.attackers lists it", node, attack)

    new_state = staticmethod(plain_vector)  # the honest State stays with the node; the lie is another vector

    def bomb(self, kind: str, maps: int) -> None:
        key = f"{kind}-{maps}"
        if key not in self.bombs:
            self.bombs[key] = bomb_payload(self.link.run, self.node, "State" if kind == "state" else "RoundComplete", maps)
        self.link.send_raw(kind, self.bombs[key])

    def send_state(self, round: int, params: np.ndarray) -> None:
        sends = self.liar.plugin.sends
        if sends in ("nothing", "metrics"):
            if sends == "metrics":
                self.inner.send_state(round, params)
            return
        if sends == "ahead":
            self.inner.send_state(round + 3, params)
            return
        if sends == "repeat":
            self.first = self.first or (round, np.array(params, copy=True))
            self.inner.send_state(*self.first)
            return
        if sends == "bomb":
            self.bomb("state", 1 << 20)
            return
        if sends == "both":
            self.inner.send_state(round, params)
        if round not in self.lies:
            self.lies = {r: v for r, v in self.lies.items() if r > round - 8}
            self.lies[round] = self.liar.lie(params)
        self.inner.send_state(round, self.lies[round])

    def send_round_complete(self, round: int) -> None:
        sends = self.liar.plugin.sends
        if sends == "bomb":
            if self.big_bombs > 0:
                self.big_bombs -= 1
                self.bomb("complete", 63 << 20)
            self.bomb("complete", 1 << 20)
        elif sends not in ("ahead", "repeat"):
            self.inner.send_round_complete(round)

    def receive(self, timeout: float) -> Envelope | None:
        return self.inner.receive(timeout)

    def lost_peers(self) -> set[int]:
        return self.inner.lost_peers()
