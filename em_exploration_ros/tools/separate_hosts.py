"""Robots on separate hosts: the lockstep team across network namespaces, against em-sim.

Each host gets its own Linux network namespace: ``<prefix>world`` (em-world, em-evaluator)
and ``<prefix>robot_<i>`` per robot. Each has its loopback and one veth interface ``eth0``
with an address in a private /24 (``--subnet``), whose other end is a port of the bridge
``br0`` in a namespace of its own (``<prefix>bridge``, multicast snooping off, so
multicast floods like on a plain switch). Nothing is created on the host's own interfaces
and no address outside that subnet is used. ``run_team.sh --netns <prefix>`` then starts
every process in its host's namespace with ``FASTDDS_BUILTIN_TRANSPORTS=UDPv4`` (no shared
memory between processes) and ``ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET`` (multicast
discovery over the bridge), in lockstep.

``--loss N`` drops about 1 packet in N leaving either end of every robot's veth (this kernel
has no netem: an ``htb`` root qdisc sends the packets a classic-BPF filter picks at random
to a class whose ``pfifo limit 0`` drops them), so world <-> robot packets cross one lossy
hop and robot <-> robot packets two; discovery is lossy too.

Afterwards em-sim's team runs in process with the same parameters (they go to run_team.sh
as one parameter file) and every robot's targets, in order, are compared with the
separate-host run's: em-sim's targets are those of the one-host ROS run of the same seed.
The namespaces and whatever still runs in them are removed on every exit path (normal
end, error, Ctrl-C, SIGTERM).

Needs root and ``ip`` with network-namespace support. Usage::

    sudo .venv/bin/python -m em_exploration_ros.tools.separate_hosts --robots 3 \\
        --map-size 50 --landmarks 4 --seed 1 [--planner EM_3] [--loss 5] [--json result.json]

Exit code: 0 same targets, 1 different targets or the team run failed, 2 cannot run here
(not root, no ``ip netns``, bad arguments).
"""
from __future__ import annotations

import ipaddress
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Sequence

from em_exploration_ros.core.params import ExplorationParams
from em_exploration_ros.core.params_yaml import dump_params
from em_exploration_ros.core.sessions.team_runner import TeamRunner
from em_exploration_ros.tools.cli_parser import CliParser
from em_exploration_ros.tools.sim_cli import add_run_arguments, params_from_args

REPO_ROOT = Path(__file__).resolve().parents[2]
RUN_TEAM = REPO_ROOT / "launch_scripts" / "run_team.sh"
DEFAULT_SUBNET = "10.213.77.0/24"
#: Bound of the team run [s] (set-up check, discovery, exploration, shutdown).
DEFAULT_TIMEOUT_S = 600.0
#: Classic BPF in tc's "count,code jt jf k,..." form: A = random; A %= N; A == 0 ? match : no.
#: 32 = LD|W|ABS (k = SKF_AD_OFF + SKF_AD_RANDOM = -4096 + 56), 148 = ALU|MOD|K,
#: 21 = JMP|JEQ|K, 6 = RET|K (-1: the filter's class, 0: no match).
RANDOM_MATCH_BPF = "5,32 0 0 4294963256,148 0 0 {n},21 0 1 0,6 0 0 4294967295,6 0 0 0"
#: Largest ``--loss`` N: the filter's modulus is a 32-bit BPF constant (tc silently truncated
#: a larger one).
MAX_LOSS_ONE_IN = 2 ** 32 - 1
#: How long run_team.sh gets to stop its processes after SIGINT [s] (its own grace periods
#: are 10 s after SIGINT and 3 s after SIGTERM).
STOP_GRACE_S = 20.0


def cannot_run_reason() -> str | None:
    """Why network namespaces cannot be made here, or None."""
    if os.geteuid() != 0:
        return "needs root (ip netns add)"
    if shutil.which("ip") is None:
        return "the ip command (iproute2) is not installed"
    probe = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True)
    if probe.returncode != 0:
        return f"ip has no network-namespace support: {probe.stderr.strip()}"
    return None


def _ip(*args: str) -> str:
    result = subprocess.run(["ip", *args], capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {result.stderr.strip()}")
    return result.stdout


def loss_problem(one_in: int) -> str | None:
    """Why ``--loss one_in`` cannot be set up, or None (0: no loss)."""
    if one_in == 0 or 2 <= one_in <= MAX_LOSS_ONE_IN:
        return None
    return f"--loss must be 0 (none) or in [2, {MAX_LOSS_ONE_IN}], got {one_in}"


def add_random_loss(namespace: str, device: str, one_in: int) -> None:
    """Drop about 1 in ``one_in`` packets leaving ``device`` of ``namespace`` (the qdisc of
    the module docstring)."""
    def tc(*args: str) -> None:
        _ip("netns", "exec", namespace, "tc", *args)
    tc("qdisc", "add", "dev", device, "root", "handle", "1:", "htb", "default", "1")
    for minor in ("1", "2"):
        tc("class", "add", "dev", device, "parent", "1:", "classid", f"1:{minor}", "htb", "rate",
           "10gbit")
    tc("qdisc", "add", "dev", device, "parent", "1:2", "handle", "20:", "pfifo", "limit", "0")
    tc("filter", "add", "dev", device, "parent", "1:", "protocol", "all", "prio", "1", "bpf",
       "bytecode", RANDOM_MATCH_BPF.format(n=one_in), "classid", "1:2")


class HostNetwork:
    """The namespaces of one world host and ``num_robots`` robot hosts on one bridge
    (module docstring), each robot's veth dropping about 1 packet in ``loss_one_in`` at both
    ends (0: none); a context manager that removes them, and every process still in them,
    on exit."""

    def __init__(self, num_robots: int, subnet: str = DEFAULT_SUBNET,
                 loss_one_in: int = 0) -> None:
        problem = loss_problem(loss_one_in)
        if problem:
            raise ValueError(problem)
        self.loss_one_in = loss_one_in
        self.prefix = f"emh{os.getpid()}_"
        self.hosts = ["world"] + [f"robot_{i}" for i in range(num_robots)]
        problem = subnet_problem(subnet, len(self.hosts))
        if problem:
            raise ValueError(problem)
        network = ipaddress.ip_network(subnet)
        hosts = network.hosts()
        self.addresses = {host: f"{next(hosts)}/{network.prefixlen}" for host in self.hosts}
        self.bridge = f"{self.prefix}bridge"
        self._created: list[str] = []

    def namespace(self, host: str) -> str:
        return f"{self.prefix}{host}"

    def __enter__(self) -> "HostNetwork":
        try:
            self._add_namespace(self.bridge)
            _ip("-n", self.bridge, "link", "add", "br0", "type", "bridge", "mcast_snooping", "0")
            _ip("-n", self.bridge, "link", "set", "br0", "up")
            for index, host in enumerate(self.hosts):
                namespace = self.namespace(host)
                self._add_namespace(namespace)
                port = f"port{index}"
                _ip("link", "add", "name", port, "netns", self.bridge, "type", "veth",
                    "peer", "name", "eth0", "netns", namespace)
                _ip("-n", self.bridge, "link", "set", port, "master", "br0", "up")
                _ip("-n", namespace, "link", "set", "lo", "up")
                _ip("-n", namespace, "addr", "add", self.addresses[host], "dev", "eth0")
                _ip("-n", namespace, "link", "set", "eth0", "up")
                # Multicast (DDS discovery) leaves through eth0; there is no default route.
                _ip("-n", namespace, "route", "add", "224.0.0.0/4", "dev", "eth0")
            for namespace, device in self._lossy_ends() if self.loss_one_in else ():
                add_random_loss(namespace, device, self.loss_one_in)
        except BaseException:
            self.__exit__()
            raise
        return self

    def bytes_through_bridge(self) -> dict[str, int]:
        """Bytes each host sent plus received through its bridge port so far."""
        result = subprocess.run(["ip", "-n", self.bridge, "-s", "-j", "link", "show"],
                                capture_output=True, text=True, check=True)
        ports = {link["ifname"]: link["stats64"] for link in json.loads(result.stdout)}
        return {host: ports[f"port{index}"]["rx"]["bytes"] + ports[f"port{index}"]["tx"]["bytes"]
                for index, host in enumerate(self.hosts)}

    def _lossy_ends(self) -> list[tuple[str, str]]:
        """(namespace, device) of both ends of every robot's veth."""
        return [end for index, host in enumerate(self.hosts) if host.startswith("robot_")
                for end in ((self.namespace(host), "eth0"), (self.bridge, f"port{index}"))]

    def drop_ratio(self) -> float:
        """Packets the lossy qdiscs dropped over packets offered to them so far (0 without
        loss)."""
        sent = dropped = 0
        for namespace, device in self._lossy_ends() if self.loss_one_in else ():
            for qdisc in json.loads(_ip("netns", "exec", namespace, "tc", "-s", "-j", "qdisc",
                                        "show", "dev", device)):
                if qdisc.get("root"):
                    sent, dropped = sent + qdisc["packets"], dropped + qdisc["drops"]
        return dropped / max(sent + dropped, 1)

    def _add_namespace(self, name: str) -> None:
        _ip("netns", "add", name)
        self._created.append(name)

    def __exit__(self, *exc: object) -> None:
        for name in reversed(self._created):
            pids = subprocess.run(["ip", "netns", "pids", name], capture_output=True,
                                  text=True).stdout.split()
            for pid in pids:  # processes this run started there and that outlived it
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except (ProcessLookupError, ValueError):
                    pass
            subprocess.run(["ip", "netns", "del", name], capture_output=True)
        self._created.clear()


@dataclass(frozen=True)
class SeparateHostsResult:
    """A separate-host run compared with em-sim: each robot's targets as ``[x, y, type]``;
    ``bridge_bytes``: bytes each host sent and received through the bridge;
    ``drop_ratio``: share of the packets the lossy links dropped (``--loss``)."""

    exit_code: int
    wall_s: float
    bridge_bytes: dict
    drop_ratio: float
    same_targets: bool
    hosts_targets: list
    em_sim_targets: list
    run_dir: str


def _targets(summary: dict) -> list:
    return [[[t["x"], t["y"], t["type"]] for t in robot["targets"]] for robot in summary["robots"]]


def subnet_problem(subnet: str, num_hosts: int) -> str | None:
    """Why ``subnet`` cannot hold ``num_hosts`` hosts, or None: it must be a private IPv4
    network (discovery goes over IPv4 multicast) written without host bits, with room for
    every host."""
    try:
        network = ipaddress.ip_network(subnet)
    except ValueError as error:
        return f"--subnet {subnet!r}: {error}"
    if network.version != 4 or not network.is_private or network.num_addresses - 2 < num_hosts:
        return (f"--subnet {subnet}: must be a private IPv4 network with room for "
                f"{num_hosts} hosts")
    return None


def run_team_apart(params: ExplorationParams, out_dir: Path, subnet: str = DEFAULT_SUBNET,
                   timeout_s: float = DEFAULT_TIMEOUT_S, domain_id: int | None = None,
                   loss_one_in: int = 0) -> SeparateHostsResult:
    """Run the lockstep team with every process on its own host (module docstring), its
    robots' links dropping about 1 packet in ``loss_one_in`` (0: none), then em-sim with
    the same parameters; compare their targets. Raises ValueError, before any namespace is
    made, when the world cannot be built from ``params``."""
    em_sim = TeamRunner(params)
    out_dir.mkdir(parents=True, exist_ok=True)
    params_file = out_dir / "params.yaml"
    params_file.write_text(dump_params(params), encoding="utf-8")
    summary_path = out_dir / "summary.json"
    command = ["bash", str(RUN_TEAM), "--params", str(params_file), "--summary",
               str(summary_path)]
    if domain_id is not None:
        command += ["--domain-id", str(domain_id)]
    with HostNetwork(params.world.num_robots, subnet, loss_one_in) as network, \
            open(out_dir / "run_team.out", "wb") as log:
        command += ["--netns", network.prefix]
        started = time.monotonic()
        team = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, start_new_session=True)
        try:
            code = team.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            code = -1
        finally:
            _stop(team)
        wall_s = time.monotonic() - started
        traffic = network.bytes_through_bridge()
        dropped = network.drop_ratio()
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else None
    hosts_targets = _targets(summary) if summary else []
    em_sim_targets = _targets(em_sim.run().to_dict())
    return SeparateHostsResult(code, wall_s, traffic, dropped, bool(hosts_targets) and
                               hosts_targets == em_sim_targets, hosts_targets,
                               em_sim_targets, str(out_dir))


def _stop(team: subprocess.Popen) -> None:
    """Stop run_team.sh if it still runs: SIGINT (it stops its nodes), then SIGKILL."""
    if team.poll() is not None:
        return
    os.killpg(team.pid, signal.SIGINT)
    try:
        team.wait(timeout=STOP_GRACE_S)
    except subprocess.TimeoutExpired:
        os.killpg(team.pid, signal.SIGKILL)
        team.wait()


def _raise_on_sigterm(signum: int, frame: object) -> None:
    raise SystemExit(128 + signum)  # unwinds through the namespaces' clean-up


def main(argv: Sequence[str] | None = None) -> int:
    parser = CliParser(description=__doc__.split("\n\n")[0])
    add_run_arguments(parser)
    parser.add_argument("--seed", type=int, default=0, help="seed of world and noise")
    parser.add_argument("--subnet", default=DEFAULT_SUBNET,
                        help=f"private subnet of the hosts (default {DEFAULT_SUBNET})")
    parser.add_argument("--loss", type=int, default=0, metavar="N",
                        help="drop about 1 packet in N at both ends of every robot's link "
                             "(default 0: none)")
    parser.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT_S,
                        help="bound of the team run [s]")
    parser.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID (default: run_team.sh's)")
    parser.add_argument("--out", type=Path, help="folder for the run (default: a new temp one)")
    parser.add_argument("--json", type=Path, help="write the result here")
    args = parser.parse_args(argv)
    reason = cannot_run_reason()
    if reason:
        print(f"separate_hosts: cannot run: {reason}", file=sys.stderr)
        return 2
    try:
        params = params_from_args(args, args.seed)
    except ValueError as error:
        parser.error(str(error))
    problem = subnet_problem(args.subnet, params.world.num_robots + 1)
    if problem:
        parser.error(problem)
    if loss_problem(args.loss):
        parser.error(loss_problem(args.loss))
    if not 0.0 < args.timeout < math.inf:
        parser.error(f"--timeout must be a positive number of seconds, got {args.timeout}")
    out = args.out or Path(tempfile.mkdtemp(prefix="separate_hosts_"))
    signal.signal(signal.SIGTERM, _raise_on_sigterm)
    try:
        result = run_team_apart(params, out, args.subnet, args.timeout, args.domain_id,
                                args.loss)
    except ValueError as error:
        parser.error(f"cannot build the world: {error}")
    counts = [len(t) for t in result.hosts_targets]
    bridge_kb = [round(b / 1000) for b in result.bridge_bytes.values()]
    print(f"separate hosts: {params.world.num_robots} robots + world, run_team.sh exit "
          f"{result.exit_code}, wall {result.wall_s:.1f} s, targets per robot {counts}, "
          f"kB through the bridge per host {bridge_kb}, "
          f"packets dropped {100 * result.drop_ratio:.1f} %; "
          f"same targets as em-sim (one host): {'yes' if result.same_targets else 'NO'}; "
          f"run in {out}")
    if args.json:
        args.json.write_text(json.dumps(asdict(result), indent=1), encoding="utf-8")
    return 0 if result.same_targets and result.exit_code == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
