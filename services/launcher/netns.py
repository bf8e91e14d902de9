"""Per-UAV network namespaces, so a `link_cut` fault can really cut a UAV off.

Each UAV's processes run in their own namespace, joined to the run's bridge by a veth
pair; the simulator and launcher stay in the root namespace and listen on the bridge's
address. Cutting a link sets the UAV's veth down and destroys the TCP connections across it
(see `cut`: a silently dead transport stalls its Zenoh peers until the lease runs out, which in
lockstep stalls the whole run). Needs root and iproute2 (`ip`, `ss`).
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
        # one /24 per run, derived from its (unique) port: 10.<hi>.<lo>.0/24
        self.prefix = f"10.{(port >> 8) & 0xFF}.{port & 0xFF}"
        self.bridge = f"{self.tag}br"
        self.host_address = f"{self.prefix}.1"
        self.uavs = list(uavs)
        self.created: list[tuple[str, str]] = []

    def namespace(self, uav: str) -> str:
        return f"falconry-{self.tag}-{uav}"

    def address(self, uav: str) -> str:
        return f"{self.prefix}.{10 + self.uavs.index(uav)}"

    def _host_veth(self, uav: str) -> str:
        return f"{self.tag}{uav}"[:15]

    def setup(self) -> None:
        try:
            _ip("link", "add", self.bridge, "type", "bridge")
            self.created.append(("link", self.bridge))
            _ip("addr", "add", f"{self.host_address}/24", "dev", self.bridge)
            _ip("link", "set", self.bridge, "up")
            for uav in self.uavs:
                ns, host_end, ns_end = self.namespace(uav), self._host_veth(uav), "eth0"
                _ip("netns", "add", ns)
                self.created.append(("netns", ns))
                _ip("link", "add", host_end, "type", "veth", "peer", "name", f"{host_end[:13]}ns")
                self.created.append(("link", host_end))
                _ip("link", "set", f"{host_end[:13]}ns", "netns", ns)
                _ip("link", "set", f"{host_end[:13]}ns", "name", ns_end, netns=ns)
                _ip("addr", "add", f"{self.address(uav)}/24", "dev", ns_end, netns=ns)
                _ip("link", "set", ns_end, "up", netns=ns)
                _ip("link", "set", "lo", "up", netns=ns)
                _ip("link", "set", host_end, "master", self.bridge)
                _ip("link", "set", host_end, "up")
        except NetnsError:
            self.teardown()
            raise

    def wrap(self, uav: str, argv: list[str]) -> list[str]:
        return ["ip", "netns", "exec", self.namespace(uav), *argv]

    def cut(self, uav: str) -> None:
        """The UAV's veth goes down, and every TCP connection across it is destroyed on both ends
        (`ss -K`): a silently dead transport would otherwise live until its lease runs out, and
        Zenoh peers block on its full queue meanwhile (a lockstep run then crawls). Partners
        therefore lose the UAV at once; nothing can reconnect until the link is restored."""
        _ip("link", "set", self._host_veth(uav), "down")
        address = self.address(uav)
        _kill_sockets(None, f"dst {address}")
        for other in self.uavs:
            if other != uav:
                _kill_sockets(self.namespace(other), f"dst {address}")
        _kill_sockets(self.namespace(uav), f"dst {self.prefix}.0/24 and not dst {address}")

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
