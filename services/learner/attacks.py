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
- ``equivocate``: two States for every round, the honest one and a ratchet's.

Each is a plug-in (an :class:`~swarmmap.shared.plugins.AttackPlugin` named in the entry-point group
``swarmmap.attacks``); another package adds its own the same way.
"""

from __future__ import annotations

import logging

import numpy as np

from swarmmap.services.learner.transport import Envelope, Transport, plain_vector
from swarmmap.shared.learning.bnn import is_rho
from swarmmap.shared.learning.layout import StateLayout
from swarmmap.shared.plugins import AttackPlugin, load

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


class HostileTransport:
    """A transport whose sender lies (:class:`Liar`) or stalls; what it receives is untouched."""

    def __init__(self, inner: Transport, node: int, attack: str, layout: StateLayout, seed: int):
        self.inner, self.node, self.attack = inner, node, attack
        self.liar = Liar(attack, layout, seed)
        self.lies: dict[int, np.ndarray] = {}  # one lie a round: a resend says the same again
        log.warning("node %d: HOSTILE: it attacks its neighbours (%s): faults.attackers lists it", node, attack)

    new_state = staticmethod(plain_vector)  # the honest State stays with the node; the lie is another vector

    def send_state(self, round: int, params: np.ndarray) -> None:
        sends = self.liar.plugin.sends
        if sends == "nothing":
            return
        if sends == "both":
            self.inner.send_state(round, params)
        if round not in self.lies:
            self.lies = {r: v for r, v in self.lies.items() if r > round - 8}
            self.lies[round] = self.liar.lie(params)
        self.inner.send_state(round, self.lies[round])

    def send_round_complete(self, round: int) -> None:
        self.inner.send_round_complete(round)

    def receive(self, timeout: float) -> Envelope | None:
        return self.inner.receive(timeout)

    def lost_peers(self) -> set[int]:
        return self.inner.lost_peers()
