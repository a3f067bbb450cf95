"""Helper process for test_zenoh_exchange: one Algorithm 1 node over a real Zenoh session.

Usage: python a1_node.py NODE ROUNDS RUN_ID ZENOH_SETTINGS_JSON OUT.npy
"""

import json
import sys
import threading

import numpy as np

from swarmmap.services.learner.algorithm1 import Algorithm1, RoundLoop
from swarmmap.services.learner.codec import StateCodec
from swarmmap.services.learner.exchange import ExchangeRules
from swarmmap.services.learner.zenoh_transport import ZenohTransport
from swarmmap.shared.run.config import ZenohSettings
from swarmmap.shared.wire.bus import Bus
from swarmmap.shared.wire.protocol import Keys


def update(node):
    def f(k, theta, peers):
        return ((theta + sum(peers.values())) / (1 + len(peers)) + 0.01 * (k + 1) * (node + 1)).astype(np.float32)
    return f


def main():
    node, rounds, run, settings, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4], sys.argv[5]
    peers = {0, 1} - {node}
    with Bus.open(ZenohSettings.model_validate(json.loads(settings)), Keys("swarmmap", run), "learner", node) as bus:
        transport = StateCodec(ZenohTransport(bus, node, peers, 4), node)
        bus.announce(service="exchange")
        assert not bus.wait_alive("exchange", {str(j) for j in peers}, 30.0)
        theta = np.full(4, float(node), np.float32)
        machine = Algorithm1(node, peers, update(node), transport, ExchangeRules(peer_timeout=30), stop=threading.Event())
        final = RoundLoop(machine).run(theta, rounds)
        np.save(out, final)


if __name__ == "__main__":
    main()
