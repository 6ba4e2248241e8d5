"""The local Ray that `arlight batch`, `arlight serve --ray local` and the tests start listens
on loopback only (issue 39, item 8): before, its GCS, raylet, runtime-env agent, driver and
workers listened on every interface (`*:PORT`), so anyone on the network could reach the
control plane. Ray starts in a child process here (`arlight.batch.init_local_ray`, the one
way the project starts a local Ray), runs one task (a worker) and one actor, and lists the
listening TCP sockets of itself and every process it started."""

from __future__ import annotations

import ipaddress
import json
import subprocess
import sys

import pytest

pytest.importorskip("ray", reason="Ray is an optional extra: pip install 'arlight[ray]'")

PROBE = r"""
import json, os, psutil, ray
from arlight.batch import init_local_ray

init_local_ray(ray, num_cpus=1)

@ray.remote
def pid():
    return os.getpid()

@ray.remote
class Actor:
    def pid(self):
        return os.getpid()

actor = Actor.remote()
ray.get([pid.remote(), actor.pid.remote()])
me = psutil.Process()
listening = []
for process in [me, *me.children(recursive=True)]:
    try:
        for c in process.net_connections(kind="tcp"):
            if c.status == psutil.CONN_LISTEN:
                listening.append([process.name(), c.laddr.ip, c.laddr.port])
    except psutil.Error:
        pass
ray.shutdown()
print(json.dumps(listening))
"""


def _loopback(ip: str) -> bool:
    address = ipaddress.ip_address(ip)
    mapped = getattr(address, "ipv4_mapped", None)  # ::ffff:127.0.0.1
    return (mapped or address).is_loopback


def test_local_ray_listens_on_loopback_only():
    run = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    listening = json.loads(run.stdout.strip().splitlines()[-1])
    names = {name for name, _, _ in listening}
    assert any("gcs_server" in n for n in names) and any("raylet" in n for n in names), names
    exposed = [s for s in listening if not _loopback(s[1])]
    assert not exposed, f"Ray listens beyond loopback: {exposed}"
