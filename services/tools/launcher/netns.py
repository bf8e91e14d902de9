"""Per-UAV network namespaces, so a `link_cut` fault can really cut a UAV off.

Each UAV's processes run in their own namespace with two links to the root namespace:
- the **radio**: a veth pair into the run's bridge (`prefix.0/25`), over which the UAV reaches
  its partners and the ground (the launcher, recorder and viewer, which listen on the bridge's
  address). A `link_cut` sets it down and destroys the TCP connections across it (see `cut`: a
  silently dead transport stalls its Zenoh peers until the lease runs out, which in lockstep
  stalls the whole run).
- the **airframe**: a point-to-point veth pair to the simulator alone (`sim_address`, a /30 in
  `prefix.128/25`), which stands for the UAV's own flight controller, sensors and clock. It is
  never cut: a real radio loss leaves a UAV its vehicle. Zenoh peers do not forward for each
  other (peer-to-peer routing), so nothing of a partner reaches the UAV through the simulator.
Needs root and iproute2 (`ip`, `ss`).
Everything is torn down at the end of the run, even after Ctrl-C.
"""
from __future__ import annotations

import os
import shutil
import subprocess


class NetnsError(RuntimeError):
    pass


def available() -> str | None:
    """None when namespaces can be used here, else why not."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    if shutil.which("ip") is None:
        return "network namespaces need iproute2 (`ip`)"
    return None


def _ip(*args: str, netns: str | None = None) -> None:
    argv = ["ip", *(("netns", "exec", netns, "ip") if netns else ()), *args]
    result = subprocess.run(argv, capture_output=True, text=True)
    if result.returncode != 0:
        raise NetnsError(f"`{' '.join(argv)}` failed: {result.stderr.strip()}")


def _kill_sockets(netns: str | None, selector: str) -> None:
    """Destroy the TCP sockets `selector` picks (needs a kernel with SOCK_DESTROY; `ss` exits 0
    without it, so what is left is checked)."""
    prefix = ["ip", "netns", "exec", netns] if netns else []
    argv = [*prefix, "ss", "-K", "-t", *selector.split()]
    result = subprocess.run(argv, capture_output=True, text=True)
    if result.returncode != 0:
        raise NetnsError(f"`{' '.join(argv)}` failed: {result.stderr.strip()}")
    left = subprocess.run([*prefix, "ss", "-H", "-t", "state", "established", *selector.split()],
                          capture_output=True, text=True).stdout.strip()
    if left:
        raise NetnsError(f"could not destroy the connections across the cut ({len(left.splitlines())} left; "
                         "does the kernel support SOCK_DESTROY?)")


class UavNetwork:
    def __init__(self, port: int, uavs: list[str]) -> None:
        self.tag = f"f{port}"
        # one /24 per run, derived from its (unique) port: 10.<hi>.<lo>.0/24, the lower half the
        # radio bridge, the upper half one /30 per UAV for its airframe link
        if len(uavs) > 31:
            raise NetnsError(f"at most 31 UAVs fit a run's address plan, not {len(uavs)}")
        self.prefix = f"10.{(port >> 8) & 0xFF}.{port & 0xFF}"
        self.bridge = f"{self.tag}br"
        self.host_address = f"{self.prefix}.1"
        self.uavs = list(uavs)
        self.created: list[tuple[str, str]] = []

    def namespace(self, uav: str) -> str:
        return f"falconry-{self.tag}-{uav}"

    def address(self, uav: str) -> str:
        return f"{self.prefix}.{10 + self.uavs.index(uav)}"

    def sim_address(self, uav: str) -> str:
        """The simulator's end of the UAV's airframe link (the UAV's end is the next address)."""
        return f"{self.prefix}.{128 + 4 * self.uavs.index(uav) + 1}"

    def _uav_sim_address(self, uav: str) -> str:
        return f"{self.prefix}.{128 + 4 * self.uavs.index(uav) + 2}"

    def _host_veth(self, uav: str) -> str:
        return f"{self.tag}{uav}"[:15]

    def _sim_veth(self, uav: str) -> str:
        return f"{self.tag}s{uav}"[:15]

    def _add_veth(self, uav: str, host_end: str, ns_end: str, ns_address: str) -> None:
        """A veth pair from the root namespace into the UAV's, `ns_end` addressed there."""
        ns = self.namespace(uav)
        _ip("link", "add", host_end, "type", "veth", "peer", "name", f"{host_end[:13]}ns")
        self.created.append(("link", host_end))
        _ip("link", "set", f"{host_end[:13]}ns", "netns", ns)
        _ip("link", "set", f"{host_end[:13]}ns", "name", ns_end, netns=ns)
        _ip("addr", "add", ns_address, "dev", ns_end, netns=ns)
        _ip("link", "set", ns_end, "up", netns=ns)

    def setup(self) -> None:
        try:
            _ip("link", "add", self.bridge, "type", "bridge")
            self.created.append(("link", self.bridge))
            _ip("addr", "add", f"{self.host_address}/25", "dev", self.bridge)
            _ip("link", "set", self.bridge, "up")
            for uav in self.uavs:
                ns, radio, airframe = self.namespace(uav), self._host_veth(uav), self._sim_veth(uav)
                _ip("netns", "add", ns)
                self.created.append(("netns", ns))
                _ip("link", "set", "lo", "up", netns=ns)
                self._add_veth(uav, radio, "eth0", f"{self.address(uav)}/25")
                _ip("link", "set", radio, "master", self.bridge)
                _ip("link", "set", radio, "up")
                self._add_veth(uav, airframe, "sim0", f"{self._uav_sim_address(uav)}/30")
                _ip("addr", "add", f"{self.sim_address(uav)}/30", "dev", airframe)
                _ip("link", "set", airframe, "up")
        except NetnsError:
            self.teardown()
            raise

    def wrap(self, uav: str, argv: list[str]) -> list[str]:
        return ["ip", "netns", "exec", self.namespace(uav), *argv]

    def cut(self, uav: str) -> None:
        """The UAV's radio veth goes down, and every TCP connection across it is destroyed on both
        ends (`ss -K`): a silently dead transport would otherwise live until its lease runs out,
        and Zenoh peers block on its full queue meanwhile (a lockstep run then crawls). Partners
        and the ground therefore lose the UAV at once; nothing can reconnect until the link is
        restored. The airframe link to the simulator stays."""
        _ip("link", "set", self._host_veth(uav), "down")
        address = self.address(uav)
        _kill_sockets(None, f"dst {address}")
        for other in self.uavs:
            if other != uav:
                _kill_sockets(self.namespace(other), f"dst {address}")
        _kill_sockets(self.namespace(uav), f"dst {self.prefix}.0/25 and not dst {address}")

    def restore(self, uav: str) -> None:
        _ip("link", "set", self._host_veth(uav), "up")

    def teardown(self) -> None:
        for kind, name in reversed(self.created):
            subprocess.run(["ip", kind, "del", name], capture_output=True)
        self.created.clear()


def leftovers(tag: str) -> list[str]:
    """Namespaces and links of a run (by its tag) that still exist: for tests."""
    names = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout.split()
    links = subprocess.run(["ip", "-o", "link"], capture_output=True, text=True).stdout
    return [n for n in names if tag in n] + [line.split(":")[1].strip() for line in links.splitlines() if tag in line]
