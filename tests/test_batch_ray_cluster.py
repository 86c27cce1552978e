"""``shadowcorr batch --engine ray`` on a three-node Ray cluster finishes every scene when a node dies mid-run.

The cluster is real: a head and two worker nodes on this machine, each started by its
own ``ray start`` with every port it opens given explicitly, so that the three do not
collide.  The head has no CPUs: every scene runs on the two worker nodes (one CPU each),
as on a cluster whose head only coordinates.  The real CLI joins it with
``--ray-address``.  Once results are being written and the doomed node is running a
scene task, that node is killed with SIGKILL (its raylet, agents and task workers, as if
its machine had gone).  Ray Data gives its tasks ``max_retries=-1`` and the engine keeps
that default, so Ray resubmits the lost node's task and the same run finishes, every
scene once, with the labels of ``shadowcorr correspond``.  (With ``max_retries=0`` on the
engine's ``map_batches`` the CLI stops at the kill with ``NodeDiedError``, exit status 1:
checked by hand, so the test can fail.)  The run then makes no progress until the GCS
declares the node dead, after its default health checks (5 failures 3 s apart, about
15 s): until then Ray Data still counts the dead node's CPU as busy.

Each node starts in a session of its own and all its processes stay in it: the session
id finds a node's processes, to kill one node and to tear the cluster down, checking
that none is left.  ``ray stop --force`` is not used: it kills every Ray process on the
machine by name, other clusters included.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np
import psutil
import pytest

from shadowcorr.cli import main
from tests.harness import REPO_ROOT
from tests.scenes import sphere_scene

VARIANTS = 3  # distinct scenes; the dataset repeats them (hard links), so each record has a reference
SCENES = 60  # enough that the run goes on well past the kill (checked)
OBJECT_STORE_BYTES = 100 * 1024 * 1024  # per node; Ray's default is 30 % of the machine's memory
GONE_WITHIN_S = 10.0
RUN_TIMEOUT_S = 240.0
RAY_CLI = [sys.executable, "-m", "ray.scripts.scripts"]  # the `ray` command, wherever its script was installed
_PORTS_PER_NODE = 6  # RayCluster._node_flags


def _free_ports(n: int) -> list[int]:
    """``n`` distinct TCP ports that were free a moment ago (all held open together, so none repeats)."""
    with ExitStack() as stack:
        socks = [stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_STREAM)) for _ in range(n)]
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [int(s.getsockname()[1]) for s in socks]


def _session_processes(sessions: set[int]) -> list[psutil.Process]:
    """The running processes whose session is one of ``sessions``."""
    found = []
    for proc in psutil.process_iter():
        try:
            if os.getsid(proc.pid) in sessions and proc.status() != psutil.STATUS_ZOMBIE:
                found.append(proc)
        except (OSError, psutil.Error):  # gone meanwhile
            pass
    return found


def _describe(procs: list[psutil.Process]) -> list[str]:
    out = []
    for proc in procs:
        try:
            out.append(f"{proc.pid} {' '.join(proc.cmdline())[:120]}")
        except psutil.Error:
            pass
    return out


@dataclass
class RayNode:
    """One ``ray start``: its session id is the pid of that command, which every process of the node keeps."""

    name: str
    session: int

    def processes(self) -> list[psutil.Process]:
        return _session_processes({self.session})

class RayCluster:
    """A head (no CPUs) and worker nodes of one CPU each, every node a ``ray start`` of its own on this machine."""

    def __init__(self, workers: int) -> None:
        self.workers_wanted = workers
        # Short: Ray's Unix sockets live under it, and a socket path has at most 107 bytes.
        self.temp_dir = tempfile.mkdtemp(prefix="rayc")
        # Every port of every node at once, so that no two of them are the same; two more: the head's GCS and
        # its dashboard (Ray starts a minimal one even with --include-dashboard=false).
        self._ports = iter(_free_ports(2 + _PORTS_PER_NODE * (1 + workers)))
        self.port = next(self._ports)
        self.address = f"127.0.0.1:{self.port}"
        self.nodes: list[RayNode] = []
        # The cluster's own settings only, none of the caller's (RAY_ADDRESS would point elsewhere).  Ray turns
        # token authentication on for a head when ~/.ray/auth_token exists and leaves it off for the nodes that
        # join: one explicit token for every node and the driver, and nothing read from or written to home.
        self.env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
        self.env.update(RAY_AUTH_MODE="token", RAY_AUTH_TOKEN=secrets.token_hex(32), RAY_USAGE_STATS_ENABLED="0")

    def _node_flags(self) -> list[str]:
        node_manager, object_manager, agent_listen, agent_grpc, runtime_env_agent, metrics = (
            next(self._ports) for _ in range(_PORTS_PER_NODE))
        # Ray turns 127.0.0.1 into the machine's own outward address (services.resolve_ip_for_localhost); the
        # worker ports (0: any free port) and these keep the nodes from fighting over Ray's fixed defaults.
        return ["--node-ip-address=127.0.0.1", f"--node-manager-port={node_manager}",
                f"--object-manager-port={object_manager}", "--min-worker-port=0", "--max-worker-port=0",
                f"--dashboard-agent-listen-port={agent_listen}", f"--dashboard-agent-grpc-port={agent_grpc}",
                f"--runtime-env-agent-port={runtime_env_agent}", f"--metrics-export-port={metrics}",
                f"--object-store-memory={OBJECT_STORE_BYTES}", "--disable-usage-stats"]

    def _start_node(self, name: str, args: list[str]) -> None:
        # A session of its own, which every process ray start daemonises keeps: the node's processes, found later.
        proc = subprocess.Popen([*RAY_CLI, "start", *args, *self._node_flags()], env=self.env, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, start_new_session=True)
        self.nodes.append(RayNode(name, proc.pid))  # before it has started: teardown ends whatever it got to start
        # ray start returns once the node has registered with the head.
        output, _ = proc.communicate(timeout=180)
        if proc.returncode != 0:
            pytest.fail(f"ray start of the {name} failed ({proc.returncode}):\n{output[-4000:]}")

    def start(self) -> None:
        self._start_node("head", ["--head", f"--port={self.port}", "--num-cpus=0", f"--temp-dir={self.temp_dir}",
                                  "--include-dashboard=false", f"--dashboard-port={next(self._ports)}"])
        # One after another: each node names its Unix sockets in the cluster's session directory after the first
        # free name (raylet, raylet.1, ...), and two nodes starting at once took the same one (the second raylet
        # aborted, "bind: Address already in use").
        for i in range(self.workers_wanted):
            self._start_node(f"worker{i}", [f"--address={self.address}", "--num-cpus=1", "--include-log-monitor=false"])

    @property
    def workers(self) -> list[RayNode]:
        return self.nodes[1:]

    def nodes_running_scenes(self) -> set[str]:
        """The worker nodes with a worker running a scene task: Ray titles a worker after the task it runs
        (``ray::MapBatches(_scenes_batch)``), an idle one ``ray::IDLE``."""
        names = {node.session: node.name for node in self.workers}
        busy = set()
        for proc in _session_processes(set(names)):
            try:
                if "_scenes_batch" in " ".join(proc.cmdline()):
                    busy.add(names[os.getsid(proc.pid)])
            except (OSError, psutil.Error):  # gone meanwhile
                pass
        return busy

    def kill_node(self, node: RayNode) -> list[psutil.Process]:
        """SIGKILL every process of the node, as if its machine had gone; returns them.

        First the raylet's process group (the raylet and its agents at once), then the workers, which Ray puts
        in process groups of their own: the cluster must see the node die, not first a worker of it.
        """
        procs = node.processes()
        os.killpg(node.session, signal.SIGKILL)
        for proc in procs:
            try:
                proc.kill()
            except psutil.NoSuchProcess:
                pass
        return procs

    def teardown(self) -> list[str]:
        """Kill every process of every node; returns those still running ``GONE_WITHIN_S`` later."""
        sessions = {node.session for node in self.nodes}
        procs = _session_processes(sessions)
        for proc in procs:
            try:
                proc.kill()  # psutil checks first that the pid is still this process
            except psutil.NoSuchProcess:
                pass
        psutil.wait_procs(procs, timeout=GONE_WITHIN_S)
        shutil.rmtree(self.temp_dir, ignore_errors=True)
        return _describe(_session_processes(sessions))


@pytest.fixture
def cluster() -> Iterator[RayCluster]:
    pytest.importorskip("ray", reason='the Ray engine needs pip install "shadowcorr[ray]"')
    ray_cluster = RayCluster(workers=2)
    try:
        ray_cluster.start()
        yield ray_cluster
    finally:
        left = ray_cluster.teardown()
        assert not left, f"still running after the cluster's teardown: {left}"


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from shadowcorr.io import write_bundle_archive

    root = tmp_path_factory.mktemp("cluster_dataset")
    rng = np.random.default_rng(5)
    base = np.array([[0.0, 0.0, 45.0], [150.0, 30.0, 45.0], [60.0, 160.0, 45.0]])
    for v in range(VARIANTS):
        centres = base + rng.uniform(-20, 20, (3, 3)) * [1, 1, 0]  # each variant's spheres moved on the ground
        write_bundle_archive(sphere_scene(centres, list(rng.uniform(38, 48, 3)), width=160, height_px=90),
                             root / f"scene_{v:03d}.zip")
    for i in range(VARIANTS, SCENES):
        os.link(root / f"scene_{i % VARIANTS:03d}.zip", root / f"scene_{i:03d}.zip")
    return root


@pytest.fixture(scope="module")
def reference(dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[int, list[int]]:
    """Labels from ``shadowcorr correspond`` on each distinct scene."""
    out = tmp_path_factory.mktemp("cluster_correspond")
    labels = {}
    for v in range(VARIANTS):
        result_file = out / f"{v}.json"
        assert main(["correspond", str(dataset / f"scene_{v:03d}.zip"), "--out", str(result_file)]) == 0
        labels[v] = [s["object"] for s in json.loads(result_file.read_text())["segments"]]
    return labels


def _lines(path: Path) -> list[str]:
    return path.read_text().splitlines() if path.exists() else []


@pytest.mark.slow
def test_batch_on_a_cluster_finishes_every_scene_when_a_node_dies(cluster: RayCluster, dataset: Path,
                                                                  reference: dict[int, list[int]],
                                                                  tmp_path: Path) -> None:
    victim, survivor = cluster.workers
    out = tmp_path / "results.jsonl"
    err_path = tmp_path / "stderr.log"
    cmd = [sys.executable, "-m", "shadowcorr.cli", "batch", str(dataset), "--out", str(out), "--engine", "ray",
           "--ray-address", cluster.address, "--no-progress"]
    with open(err_path, "wb") as err:
        # Its own session: a Ctrl-C of the test run does not reach it, and the finally below finds what it left.
        driver = subprocess.Popen(cmd, cwd=REPO_ROOT, env=cluster.env, stdout=subprocess.DEVNULL, stderr=err,
                                  start_new_session=True)
    busy_seen: set[str] = set()  # worker nodes seen running a scene task before the kill
    try:
        deadline = time.monotonic() + RUN_TIMEOUT_S
        # Kill once scenes are being written and the victim is in the middle of a task: a task of the lost
        # node must be redone elsewhere, and the run must not be over already.
        while True:
            assert driver.poll() is None, f"the run ended before the kill:\n{err_path.read_text()}"
            assert time.monotonic() < deadline, f"no scene done in time:\n{err_path.read_text()}"
            busy_now = cluster.nodes_running_scenes()
            busy_seen |= busy_now
            if victim.name in busy_now and _lines(out):
                break
            time.sleep(0.05)
        written_before_kill = len(_lines(out))
        victim_procs = cluster.kill_node(victim)
        assert victim_procs, "the node had processes"
        _, alive = psutil.wait_procs(victim_procs, timeout=GONE_WITHIN_S)
        assert not alive, f"the killed node's processes still run: {_describe(alive)}"
        status = driver.wait(timeout=max(deadline - time.monotonic(), 1.0))
    finally:
        left = _session_processes({driver.pid})  # the driver itself too, if a check above stopped the test
        for proc in left:
            try:
                proc.kill()
            except psutil.NoSuchProcess:
                pass
        driver.wait()
    stderr = err_path.read_text()
    assert not left, f"the driver left processes behind: {_describe(left)}"
    assert written_before_kill < SCENES, "the node died mid-run"
    assert status == 0, stderr
    assert busy_seen == {victim.name, survivor.name}, "scenes ran on both worker nodes"
    assert survivor.processes(), "the other worker node ran on"
    records = [json.loads(line) for line in _lines(out)]
    names = sorted(r["scene"] for r in records)
    assert names == [f"scene_{i:03d}.zip" for i in range(SCENES)], "every scene exactly once"
    assert all(r["status"] == "ok" for r in records), stderr
    for r in records:
        variant = int(r["scene"][len("scene_"):-len(".zip")]) % VARIANTS
        assert [s["object"] for s in r["result"]["segments"]] == reference[variant], r["scene"]
