"""Hosts on one machine: each robot's services in a network namespace of its own (``up --netns``).

A team of N robots gets N+1 hosts (shared/wire/mesh.py): the base host is this machine's own network
stack (the world, the recorder, the observer and ``up``, so the viewer stays on loopback), and
each robot host ``r<i>`` a namespace ``swarmmap-<tag>-r<i>`` (``tag``: six hex digits of the
run id). They are joined by a bridge that lives in a namespace of its own, the switch
(``swarmmap-<tag>-sw``), so that no rule of this machine's firewall (Docker's FORWARD policy,
say) sees their traffic. Every host has one link to the switch, a veth pair, and an address in
a private /24 (``10.<a>.<b>.0/24``, one that no interface here uses): the base ``.1``, robot
``i`` ``.(i+2)``.

Links are shaped on both ends of each robot's veth pair, each way on its own: a rate with
``tc tbf`` (``--link-rate``), packet loss with an nftables ``numgen random`` rule on the robot's
interface (``--link-loss``, each way; loopback inside a host is never touched). A partition
(:meth:`Network.cut`) drops, in each robot host, the packets to and from the hosts on the other
side; :meth:`Network.heal` removes it. ``swarmmap net`` does the same from another shell while a
run goes on (the fault harness).

Everything is removed when the run ends: by ``up`` itself, and, when ``up`` is killed (even by
SIGKILL), by a guard process that waits for it to die (``python -m swarmmap.services.up.netns
guard``). Deleting a namespace removes its interfaces, their qdiscs and its rules. What exists is
written to ``RUN_DIR/network.json`` first, so a later ``up --netns`` of the run, or ``swarmmap
net clean``, can remove what a crash left.
"""

from __future__ import annotations

import argparse
import hashlib
import ipaddress
import json
import logging
import os
import shutil
import subprocess
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path

from swarmmap.shared.run.atomic import atomic_write_text
from swarmmap.shared.run.runtime import wait_for_exit
from swarmmap.shared.wire.mesh import BASE, host_names

log = logging.getLogger("netns")
STATE_FILE = "network.json"
ROUTER_PORT = 7447  # a robot host's router, on its own address and its loopback


class NetnsError(RuntimeError):
    """A namespace, interface or rule that could not be made; the message names the command and what it said."""


def sh(*args: str, stdin: str | None = None, check: bool = True) -> subprocess.CompletedProcess:
    """Run one command of ``ip``, ``tc`` or ``nft``; raises NetnsError naming it when it fails."""
    try:
        done = subprocess.run(list(args), input=stdin, capture_output=True, text=True, timeout=30)
    except FileNotFoundError:
        raise NetnsError(f"{args[0]} is not installed (iproute2 and nftables are needed for --netns)") from None
    if check and done.returncode != 0:
        raise NetnsError(f"`{' '.join(args)}` failed: {(done.stderr or done.stdout).strip()}")
    return done


def tag_of(run_id: str) -> str:
    """Six hex digits naming the run's namespaces and interfaces (Linux allows 15 characters a name)."""
    return hashlib.sha256(run_id.encode()).hexdigest()[:6]


def used_networks() -> list[ipaddress.IPv4Network]:
    """The IPv4 networks of this machine's interfaces."""
    out = sh("ip", "-4", "-o", "addr", "show", check=False).stdout
    nets = []
    for line in out.splitlines():
        parts = line.split()
        if "inet" in parts:
            nets.append(ipaddress.ip_interface(parts[parts.index("inet") + 1]).network)
    return nets


def free_subnet(tag: str) -> ipaddress.IPv4Network:
    """A /24 in 10.0.0.0/8 that overlaps none of this machine's networks, first tried from ``tag``."""
    used = used_networks()
    start = int(tag, 16) % (200 * 250)
    for k in range(200 * 250):
        n = (start + k) % (200 * 250)
        net = ipaddress.ip_network(f"10.{50 + n // 250}.{n % 250}.0/24")
        if not any(net.overlaps(u) for u in used):
            return net
    raise NetnsError("no free /24 in 10.50.0.0-10.249.249.0 for the run's hosts")


def check_rate(rate: str) -> int:
    """``rate`` (``1mbit``, ``512kbit``) in bits per second."""
    units = {"bit": 1, "kbit": 1_000, "mbit": 1_000_000, "gbit": 1_000_000_000}
    for unit in sorted(units, key=len, reverse=True):
        if rate.endswith(unit):
            return int(float(rate[: -len(unit)]) * units[unit])
    raise NetnsError(f"link rate {rate!r}: give bits per second as e.g. 100mbit, 10mbit, 512kbit")


@dataclass
class Network:
    """The hosts of one run: the switch, a namespace per robot host, their addresses and links."""

    run_id: str
    robots: int
    state_path: Path
    tag: str = ""
    subnet: str = ""
    cut_hosts: list[str] = field(default_factory=list)
    rate: str | None = None
    loss: float = 0.0

    def __post_init__(self) -> None:
        self.tag = self.tag or tag_of(self.run_id)

    # ------------------------------------------------------------------ names
    @property
    def switch(self) -> str:
        return f"swarmmap-{self.tag}-sw"

    def namespace(self, host: str) -> str | None:
        """The namespace of ``host`` (None for the base: this machine's own stack)."""
        return None if host == BASE else f"swarmmap-{self.tag}-{host}"

    def namespaces(self) -> list[str]:
        return [self.switch] + [self.namespace(h) for h in host_names(self.robots)[1:]]

    def veth(self, host: str, side: str) -> str:
        """``host``'s end (``side`` h) or the switch's end (``side`` s) of its link."""
        return f"sm{self.tag}{side}{'b' if host == BASE else host[1:]}"

    def address(self, host: str) -> str:
        """``host``'s address on the run's network."""
        net = ipaddress.ip_network(self.subnet)
        return str(net.network_address + (1 if host == BASE else int(host[1:]) + 2))

    def prefix(self, host: str) -> list[str]:
        """The command prefix that runs a program on ``host``."""
        ns = self.namespace(host)
        return [] if ns is None else ["ip", "netns", "exec", ns]

    # ------------------------------------------------------------------ life
    def save(self) -> None:
        atomic_write_text(self.state_path, json.dumps({
            "run_id": self.run_id, "robots": self.robots, "tag": self.tag, "subnet": self.subnet,
            "namespaces": self.namespaces(), "hosts": {h: self.address(h) for h in host_names(self.robots)},
            "cut": self.cut_hosts, "rate": self.rate, "loss": self.loss}, indent=2) + "\n")

    @classmethod
    def load(cls, state_path: Path) -> Network:
        """The network a run wrote in ``state_path``; raises NetnsError when there is none."""
        try:
            doc = json.loads(state_path.read_text())
            return cls(doc["run_id"], int(doc["robots"]), state_path, doc["tag"], doc["subnet"], list(doc.get("cut", [])),
                       doc.get("rate"), float(doc.get("loss", 0.0)))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise NetnsError(f"{state_path}: no network of a run ({exc})") from None

    def create(self) -> None:
        """Make the switch, the robot hosts and their links; on a failure, remove what was made."""
        if missing := [tool for tool in ("ip", "tc", "nft") if shutil.which(tool) is None]:
            raise NetnsError(f"{', '.join(missing)} not installed: --netns needs iproute2 (ip, tc) and nftables (nft), "
                             f"e.g. `apt-get install iproute2 nftables`")
        self.remove(quiet=True)  # what an earlier attempt of this run left, if anything
        self.subnet = self.subnet or str(free_subnet(self.tag))
        prefix = ipaddress.ip_network(self.subnet).prefixlen
        self.save()  # first: whatever is made below can be found and removed
        try:
            sh("ip", "netns", "add", self.switch)
            sw = ["ip", "-n", self.switch]
            sh(*sw, "link", "add", "br0", "type", "bridge")
            sh(*sw, "link", "set", "br0", "up")
            for host in host_names(self.robots):
                inner, outer = self.veth(host, "h"), self.veth(host, "s")
                if host == BASE:
                    sh("ip", "link", "add", inner, "type", "veth", "peer", "name", outer, "netns", self.switch)
                    sh("ip", "addr", "add", f"{self.address(host)}/{prefix}", "dev", inner)
                    sh("ip", "link", "set", inner, "up")
                else:
                    ns = self.namespace(host)
                    sh("ip", "netns", "add", ns)
                    sh("ip", "-n", ns, "link", "add", inner, "type", "veth", "peer", "name", outer, "netns", self.switch)
                    sh("ip", "-n", ns, "addr", "add", f"{self.address(host)}/{prefix}", "dev", inner)
                    sh("ip", "-n", ns, "link", "set", inner, "up")
                    sh("ip", "-n", ns, "link", "set", "lo", "up")
                sh(*sw, "link", "set", outer, "master", "br0")
                sh(*sw, "link", "set", outer, "up")
            self.shape(self.rate, self.loss)
        except NetnsError:
            self.remove(quiet=True)
            raise
        log.info("network %s: base %s, robot hosts %s in namespaces swarmmap-%s-r<i>, joined by a switch (%s)%s", self.subnet,
                 self.address(BASE), ", ".join(f"r{i} {self.address(f'r{i}')}" for i in range(self.robots)), self.tag, self.switch,
                 self.link_words())

    def link_words(self) -> str:
        what = ([f"{self.rate} each way"] if self.rate else []) + ([f"{self.loss:.1%} loss each way"] if self.loss else [])
        return f"; every robot link {', '.join(what)}" if what else ""

    def remove(self, quiet: bool = False) -> list[str]:
        """Delete the run's namespaces (their interfaces, qdiscs and rules go with them) and the
        base's link; returns what was removed."""
        present = set(sh("ip", "netns", "list", check=False).stdout.split())
        gone = []
        for ns in self.namespaces():
            if ns in present:
                sh("ip", "netns", "del", ns, check=False)
                gone.append(ns)
        base = self.veth(BASE, "h")
        if sh("ip", "link", "show", base, check=False).returncode == 0:
            sh("ip", "link", "del", base, check=False)
            gone.append(base)
        if gone and not quiet:
            log.info("network of run %s removed: %s", self.run_id, ", ".join(gone))
        return gone

    # ------------------------------------------------------------------ links
    def shape(self, rate: str | None, loss: float, hosts: list[str] | None = None) -> None:
        """Set each robot host's link (all, or ``hosts``) to ``rate`` (None: unlimited) and
        ``loss`` (a share of packets, each way)."""
        hosts = hosts or host_names(self.robots)[1:]
        if bad := [h for h in hosts if h not in host_names(self.robots)[1:]]:
            raise NetnsError(f"hosts {bad}: the robot hosts are {', '.join(host_names(self.robots)[1:])}")
        for host in hosts:
            ends = [(["ip", "netns", "exec", self.namespace(host)], self.veth(host, "h")),
                    (["ip", "netns", "exec", self.switch], self.veth(host, "s"))]
            for pre, dev in ends:
                sh(*pre, "tc", "qdisc", "del", "dev", dev, "root", check=False)
                if rate:
                    bps = check_rate(rate)
                    burst = max(32_000, bps // 8 // 50)  # bytes: at least 20 ms of the rate
                    sh(*pre, "tc", "qdisc", "add", "dev", dev, "root", "tbf", "rate", rate, "burst", str(burst), "latency", "400ms")
            self.rules(host, loss)
        if hosts == host_names(self.robots)[1:]:
            self.rate, self.loss = rate, loss
        self.save()

    def rules(self, host: str, loss: float) -> None:
        """The nftables table of ``host``: its loss, and the partition when one is in force."""
        dev = self.veth(host, "h")
        lines = ["table inet swarmmap", "delete table inet swarmmap", "table inet swarmmap {",
                 "  chain out { type filter hook output priority 0; policy accept; }",
                 "  chain in { type filter hook input priority 0; policy accept; }", "}"]
        if loss:
            n = round(loss * 1_000_000)
            lines += [f'add rule inet swarmmap out oifname "{dev}" numgen random mod 1000000 < {n} drop',
                      f'add rule inet swarmmap in iifname "{dev}" numgen random mod 1000000 < {n} drop']
        if self.cut_hosts:
            inside = host in self.cut_hosts
            others = [self.address(h) for h in host_names(self.robots) if (h in self.cut_hosts) != inside]
            if others:
                addrs = ", ".join(others)
                lines += [f"add rule inet swarmmap out ip daddr {{ {addrs} }} drop",
                          f"add rule inet swarmmap in ip saddr {{ {addrs} }} drop"]
        sh("ip", "netns", "exec", self.namespace(host), "nft", "-f", "-", stdin="\n".join(lines) + "\n")

    def cut(self, hosts: list[str]) -> None:
        """Partition the team: ``hosts`` on one side, every other host on the other; nothing
        passes between them until :meth:`heal`."""
        bad = [h for h in hosts if h not in host_names(self.robots)]
        if bad or not hosts or set(hosts) == set(host_names(self.robots)):
            raise NetnsError(f"cut {hosts}: name some, not all, of the hosts {', '.join(host_names(self.robots))}")
        self.cut_hosts = sorted(set(hosts))
        for host in host_names(self.robots)[1:]:
            self.rules(host, self.loss)
        self.save()
        log.warning("network of run %s cut: %s | %s", self.run_id, " ".join(self.cut_hosts),
                    " ".join(h for h in host_names(self.robots) if h not in self.cut_hosts))

    def heal(self) -> None:
        """End the partition."""
        self.cut_hosts = []
        for host in host_names(self.robots)[1:]:
            self.rules(host, self.loss)
        self.save()
        log.warning("network of run %s healed", self.run_id)


# ---------------------------------------------------------------------- swarmmap net

def add_net_arguments(p: argparse.ArgumentParser) -> None:
    """``swarmmap net``'s arguments."""
    p.add_argument("run_dir", type=Path, metavar="RUN_DIR", help="the run directory of a run started with up --netns")
    sub = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    cut = sub.add_parser("cut", help="partition the team: these hosts on one side, the rest on the other")
    cut.add_argument("hosts", nargs="+", metavar="HOST", help="hosts (base, r0, r1, ...)")
    cut.add_argument("--for", dest="for_s", type=float, default=None, metavar="S", help="heal it after S seconds")
    sub.add_parser("heal", help="end the partition")
    shape = sub.add_parser("shape", help="set the robot hosts' link rate and loss")
    shape.add_argument("--rate", default=None, help="rate each way, e.g. 1mbit (default: unlimited)")
    shape.add_argument("--loss", type=float, default=0.0, help="share of packets lost each way, e.g. 0.01")
    shape.add_argument("--hosts", nargs="+", default=None, metavar="HOST", help="only these robot hosts")
    sub.add_parser("show", help="the run's hosts, addresses, partition and links")
    sub.add_parser("clean", help="remove what a run that crashed left (namespaces, links)")


def run_net(args: argparse.Namespace, stop: threading.Event) -> int:
    """``swarmmap net RUN_DIR ACTION``: change a running team's network (the fault harness)."""
    logging.basicConfig(level="INFO", format="%(asctime)s %(levelname)s net: %(message)s")
    try:
        net = Network.load(args.run_dir / STATE_FILE)
        if args.action == "show":
            print(json.dumps(json.loads(net.state_path.read_text()), indent=2))
            return 0
        if args.action == "clean":
            print(f"removed: {', '.join(net.remove(quiet=True)) or 'nothing was left'}")
            return 0
        if os.geteuid() != 0:
            raise NetnsError("changing a run's network needs root")
        present = set(sh("ip", "netns", "list", check=False).stdout.split())
        if net.switch not in present:
            raise NetnsError(f"the network of run {net.run_id} is gone: the run is over")
        if args.action == "cut":
            net.cut(args.hosts)
            if args.for_s is not None:
                stop.wait(args.for_s)
                net.heal()
        elif args.action == "heal":
            net.heal()
        else:
            if args.rate is not None:
                check_rate(args.rate)
            if not 0 <= args.loss < 1:
                raise NetnsError(f"--loss {args.loss}: a share of packets, at least 0 and below 1")
            net.shape(args.rate, args.loss, args.hosts)
    except NetnsError as exc:
        print(f"swarmmap net: {exc}", file=sys.stderr)
        return 2
    return 0


# ---------------------------------------------------------------------- the guard

def start_guard(state_path: Path, log_path: Path) -> subprocess.Popen:
    """Start the process that removes the run's network once this process has died, however it died."""
    with log_path.open("a") as out:
        return subprocess.Popen([sys.executable, "-m", "swarmmap.services.up.netns", "guard", str(os.getpid()), str(state_path)],
                                stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)


def guard(pid: int, state_path: Path) -> int:
    """Wait until process ``pid`` has ended, then remove the network in ``state_path`` (if any is left)."""
    wait_for_exit(pid)
    try:
        net = Network.load(state_path)
    except NetnsError:
        return 0
    gone = net.remove(quiet=True)
    if gone:
        log.warning("up (pid %d) ended without removing its network: removed %s", pid, ", ".join(gone))
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m swarmmap.services.up.netns guard PID STATE``: the guard (see :func:`guard`)."""
    p = argparse.ArgumentParser(prog="swarmmap.services.up.netns")
    sub = p.add_subparsers(dest="command", required=True)
    g = sub.add_parser("guard")
    g.add_argument("pid", type=int)
    g.add_argument("state", type=Path)
    args = p.parse_args(argv)
    logging.basicConfig(level="INFO", format="%(asctime)s %(levelname)s netns-guard: %(message)s")
    return guard(args.pid, args.state)


if __name__ == "__main__":
    sys.exit(main())
