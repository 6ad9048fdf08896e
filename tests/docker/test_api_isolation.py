"""The compose coordinator's API is out of reach of run containers, and within reach of the host.

The coordinator container joins every run network (federates reach its zenoh router there, under
the alias ``coordinator``), so its API must not listen on those networks. This starts the runtime
image with the coordinator's listen arguments and platform-network alias taken from
docker-compose.yml, connects it to a run network the way the docker launcher does, and probes
the API from both sides and through its published port: Docker moves published ports to the
first of a container's networks by name, which must stay the platform network."""

from __future__ import annotations

import json
import time
import urllib.request
import uuid
from pathlib import Path
from typing import Any

import pytest
import yaml

from coordinator.docker_runs import LABEL_RUN
from coordinator.runtime_docker import RUNTIME_IMAGE

pytestmark = pytest.mark.docker
COMPOSE = Path(__file__).parents[2] / "docker-compose.yml"
TOKEN = "isolation-token-0123456789abcdef"
API_PORT = 8080

PROBE = """
import json, socket, sys, urllib.error, urllib.request
host, port, token = sys.argv[1], int(sys.argv[2]), sys.argv[3]
out = {}
try:
    out["address"] = socket.gethostbyname(host)
except OSError as e:
    out["address"] = f"unresolved: {e}"
for name, headers in (("healthz", {}), ("runs_without_token", {}), ("runs", {"Authorization": "Bearer " + token})):
    path = "/healthz" if name == "healthz" else "/runs"
    req = urllib.request.Request(f"http://{host}:{port}{path}", headers=headers)
    try:
        out[name] = urllib.request.urlopen(req, timeout=5).status
    except urllib.error.HTTPError as e:
        out[name] = e.code
    except OSError as e:
        reason = getattr(e, "reason", e)
        out[name] = "refused" if isinstance(reason, ConnectionRefusedError) else f"error: {reason}"
print(json.dumps(out))
"""


def compose_coordinator() -> tuple[list[str], list[str], str]:
    """The coordinator's ``--host`` values, its aliases on the platform network, and that
    network's name."""
    compose = yaml.safe_load(COMPOSE.read_text())
    svc = compose["services"]["coordinator"]
    hosts = [a.split("=", 1)[1] for a in svc["command"] if a.startswith("--host=")]
    aliases = svc.get("networks", {}).get("default", {}).get("aliases", [])
    return hosts, aliases, compose.get("networks", {}).get("default", {}).get("name", "")


def probe(client: Any, network: str, host: str, run_id: str) -> dict[str, Any]:
    out = client.containers.run(RUNTIME_IMAGE, ["python", "-c", PROBE, host, str(API_PORT), TOKEN], network=network,
                                labels={LABEL_RUN: run_id}, remove=True, read_only=True,
                                cap_drop=["ALL"], tmpfs={"/tmp": ""})
    return dict(json.loads(out.decode().strip().splitlines()[-1]))


def test_run_containers_cannot_reach_the_api(docker_client: Any, run_id: str) -> None:
    hosts, aliases, platform_name = compose_coordinator()
    assert hosts and "0.0.0.0" not in hosts and "::" not in hosts, f"the API listens everywhere: {hosts}"
    assert aliases, "docker-compose.yml gives the coordinator no platform-network alias to listen on"
    # Run networks are cosim5g-<run_id>: the platform network must sort before every one of them.
    assert platform_name and platform_name < "cosim5g-", platform_name
    labels = {LABEL_RUN: run_id}
    # Not the compose network itself (a platform may be up), but named to sort as it does.
    platform = docker_client.networks.create(f"cosim5-test-{uuid.uuid4().hex[:8]}", driver="bridge",
                                             labels=labels)
    coordinator = docker_client.containers.create(
        RUNTIME_IMAGE,
        ["cosim5g", "serve", *(f"--host={h}" for h in hosts), f"--port={API_PORT}",
         "--results=/tmp/r/runs", "--db=/tmp/r/cosim5g.db", "--sweeps=/tmp/r/sweeps",
         "--scenarios=/tmp/none", "--sweep-specs=/tmp/none", "--token-file=/tmp/r/auth/api-token"],
        name=f"cosim5g-{run_id}-coordinator", labels=labels, environment={"COSIM5G_TOKEN": TOKEN},
        read_only=True, tmpfs={"/tmp": ""}, cap_drop=["ALL"], network=platform.name,
        ports={f"{API_PORT}/tcp": ("127.0.0.1", None)})
    # Aliases are set per network at connect time: reconnect with the platform-network alias.
    platform.disconnect(coordinator)
    platform.connect(coordinator, aliases=aliases)
    coordinator.start()
    deadline = time.monotonic() + 90
    while True:
        code, _ = coordinator.exec_run(["python", "-c", "import urllib.request; urllib.request.urlopen("
                                        f"'http://127.0.0.1:{API_PORT}/healthz', timeout=3)"])
        if code == 0:
            break
        coordinator.reload()
        assert coordinator.status == "running", coordinator.logs().decode()[-2000:]
        assert time.monotonic() < deadline, coordinator.logs().decode()[-2000:]
        time.sleep(1.0)

    # A run network, joined by the coordinator as DockerLauncher does it (alias "coordinator").
    run_net = docker_client.networks.create(f"cosim5g-{run_id}", driver="bridge", labels=labels)
    run_net.connect(coordinator, aliases=["coordinator"])

    from_run = probe(docker_client, run_net.name, "coordinator", run_id)
    # The coordinator is on the run network (its name resolves, the connection is actively
    # refused rather than lost), but nothing of the API answers there.
    assert not str(from_run["address"]).startswith("unresolved"), from_run
    assert from_run == {"address": from_run["address"], "healthz": "refused", "runs_without_token": "refused",
                        "runs": "refused"}

    from_platform = probe(docker_client, platform.name, aliases[0], run_id)
    assert from_platform == {"address": from_platform["address"], "healthz": 200, "runs_without_token": 401,
                             "runs": 200}

    # The host, through the published port, while the coordinator is on the run network.
    coordinator.reload()
    host_port = coordinator.attrs["NetworkSettings"]["Ports"][f"{API_PORT}/tcp"][0]["HostPort"]
    with urllib.request.urlopen(f"http://127.0.0.1:{host_port}/healthz", timeout=10) as resp:
        assert resp.status == 200


PROMETHEUS_PROBE = """
import json, sys, urllib.error, urllib.request
try:
    out = urllib.request.urlopen(f"http://{sys.argv[1]}:9090/-/ready", timeout=5).status
except urllib.error.HTTPError as e:
    out = e.code
except OSError as e:
    reason = getattr(e, "reason", e)
    out = "refused" if isinstance(reason, ConnectionRefusedError) else f"error: {reason}"
print(json.dumps(out))
"""


def test_run_containers_cannot_reach_prometheus(docker_client: Any, run_id: str) -> None:
    """Prometheus joins every run network to scrape federates; its API listens on the platform
    network only (docker-compose.yml's entrypoint), so run containers cannot query it."""
    svc = yaml.safe_load(COMPOSE.read_text())["services"]["prometheus"]
    [alias] = svc["networks"]["default"]["aliases"]
    # What compose runs ("$$" is its escape of "$"), with an empty configuration and data in /tmp.
    script = "printf 'global: {}\\n' > /tmp/p.yml; " + svc["command"][0].replace("$$", "$").replace(
        "/etc/prometheus/prometheus.yml", "/tmp/p.yml").replace("tsdb.path=/prometheus", "tsdb.path=/tmp/data")
    labels = {LABEL_RUN: run_id}
    platform = docker_client.networks.create(f"cosim5-test-{uuid.uuid4().hex[:8]}", driver="bridge", labels=labels)
    prom = docker_client.containers.create(svc["image"], [script], entrypoint=svc["entrypoint"],
                                           name=f"cosim5g-{run_id}-prometheus", labels=labels, read_only=True,
                                           tmpfs={"/tmp": ""}, cap_drop=["ALL"], network=platform.name)
    platform.disconnect(prom)
    platform.connect(prom, aliases=[alias])
    prom.start()
    deadline = time.monotonic() + 90
    while prom.exec_run(["wget", "-q", "-O", "/dev/null", f"http://{alias}:9090/-/ready"])[0] != 0:
        prom.reload()
        assert prom.status == "running", prom.logs().decode()[-2000:]
        assert time.monotonic() < deadline, prom.logs().decode()[-2000:]
        time.sleep(1.0)
    run_net = docker_client.networks.create(f"cosim5g-{run_id}", driver="bridge", labels=labels)
    run_net.connect(prom, aliases=["prometheus"])

    def probe_from(network: str, host: str) -> Any:
        out = docker_client.containers.run(RUNTIME_IMAGE, ["python", "-c", PROMETHEUS_PROBE, host], network=network,
                                           labels=labels, remove=True, read_only=True, cap_drop=["ALL"],
                                           tmpfs={"/tmp": ""})
        return json.loads(out.decode().strip().splitlines()[-1])

    assert probe_from(run_net.name, "prometheus") == "refused"
    assert probe_from(platform.name, alias) == 200
