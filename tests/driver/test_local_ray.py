"""Local Ray's object store fits the /dev/shm it is given (a container's --shm-size)."""

from __future__ import annotations

import os

import pytest

from driver.local_ray import RAY_MIN_OBJECT_STORE, _shm_free, object_store_bytes

GIB = 1024**3


def test_a_small_shm_gets_a_store_that_fits_it():
    # docker run --shm-size=2g on a 24 GiB host: Ray's default (7.2 GiB) would go to /tmp
    size = object_store_bytes(shm_free=2 * GIB, memory=24 * GIB)
    assert size is not None and RAY_MIN_OBJECT_STORE <= size <= 2 * GIB


def test_a_large_shm_keeps_rays_default():
    assert object_store_bytes(shm_free=12 * GIB, memory=24 * GIB) is None


def test_below_rays_minimum_ray_decides():
    # Docker's default 64 MB: nothing fits; Ray falls back to /tmp and says how to fix it
    assert object_store_bytes(shm_free=64 * 1024**2, memory=24 * GIB) is None


def test_reads_this_machines_shm():
    assert _shm_free() > 0


def test_local_mode_gives_rays_gcs_time_on_a_busy_machine(monkeypatch):
    import ray

    from driver import local_ray

    started = {}
    monkeypatch.delenv(local_ray.GCS_WAIT, raising=False)
    monkeypatch.setattr(ray, "init", lambda **kwargs: started.update(kwargs))
    local_ray.init_local_ray(2)
    assert started["num_cpus"] == 2
    assert int(os.environ[local_ray.GCS_WAIT]) >= 120  # Ray's own: 30 s
    monkeypatch.setenv(local_ray.GCS_WAIT, "45")  # the user's choice stands
    local_ray.init_local_ray(2)
    assert os.environ[local_ray.GCS_WAIT] == "45"


def test_local_ray_runs_actors_without_the_helpers_it_does_not_use(ray_session):
    from driver.local_ray import LEAN_PROCESSES

    node = ray_session._private.worker._global_node
    started = set(node.all_processes)
    assert {"gcs_server", "raylet"} <= started
    assert not started & set(LEAN_PROCESSES)
    assert node.webui_url is None  # no dashboard, and Ray knows it

    @ray_session.remote(num_cpus=0)
    def pid() -> int:
        return os.getpid()

    assert ray_session.get(pid.remote()) != os.getpid()  # a worker process answered


def test_the_lean_head_puts_rays_hooks_back_even_when_init_fails():
    import pytest
    import ray._private.node
    import ray._private.services

    from driver.local_ray import _lean_head

    node, get_node = ray._private.node.Node, ray._private.services.get_node
    with pytest.raises(RuntimeError), _lean_head():
        assert issubclass(ray._private.node.Node, node) and ray._private.node.Node is not node
        raise RuntimeError("ray.init failed")
    assert ray._private.node.Node is node and ray._private.services.get_node is get_node


def test_a_ray_whose_internals_moved_still_starts_the_plain_way(monkeypatch):
    import ray
    import ray._private.node

    from driver import local_ray

    plain = ray._private.node.Node
    calls: list[bool] = []

    def init(**kwargs: object) -> None:
        calls.append(ray._private.node.Node is plain)
        if len(calls) == 1:
            raise TypeError("Node.__init__() got an unexpected keyword argument")

    monkeypatch.setattr(ray, "init", init)
    monkeypatch.setattr(ray._private.worker, "_global_node", None)  # the lean try started none
    local_ray.init_local_ray(2)
    assert calls == [False, True]  # the lean try, then Ray as it comes


def _dying_raylets(monkeypatch, deaths: int, plain_fails: bool) -> list[bool]:
    """``ray.init`` whose lean heads' raylets die ``deaths`` times; then a lean start that
    works, or (``plain_fails``) Ray's full head timing out. Returns each call's leanness."""
    import ray
    import ray._private.node

    from driver import local_ray

    plain = ray._private.node.Node
    calls: list[bool] = []

    def init(**kwargs: object) -> None:
        lean = ray._private.node.Node is not plain
        calls.append(lean)
        if lean and calls.count(True) <= deaths:
            raise local_ray.RayletExited("exit 1: Timed out waiting for file metrics_agent_port")
        if not lean and plain_fails:
            raise Exception("The current node timed out during startup. This could\nhappen")

    monkeypatch.setattr(ray, "init", init)
    monkeypatch.setattr(ray._private.worker, "_global_node", None)
    return calls


def test_raylets_that_keep_dying_are_started_again_until_the_start_wait_is_spent(monkeypatch):
    from driver import local_ray

    calls = _dying_raylets(monkeypatch, deaths=5, plain_fails=True)
    local_ray.init_local_ray(2)  # five deaths within START_WAIT_S: a sixth lean start
    assert calls == [True] * 6


def test_a_ray_that_never_starts_is_one_line_saying_what_was_waited_for(monkeypatch):
    from driver import local_ray

    monkeypatch.setattr(local_ray, "START_WAIT_S", 0)  # spent: LEAN_TRIES, then Ray's head
    calls = _dying_raylets(monkeypatch, deaths=99, plain_fails=True)
    with pytest.raises(local_ray.RayStartError) as error:
        local_ray.init_local_ray(2)
    assert calls == [True] * local_ray.LEAN_TRIES + [False]
    message = str(error.value)
    assert "\n" not in message, message
    assert f"its raylet died {local_ray.LEAN_TRIES} times before registering" in message
    assert "metrics_agent_port" in message
    assert "Ray's own start said: The current node timed out during startup." in message


# In a process of its own: the session's Ray is left alone. The first head's raylet start
# fails after its GCS is up (as when a raylet never registers on a loaded machine).
HALF_STARTED_HEAD = """
import json, logging, psutil, ray, ray._private.node as node
from driver import local_ray
logging.disable(logging.WARNING)
plain, first = node.Node.start_ray_processes, []
def once(self):
    if first:
        return plain(self)
    first.extend(i.process.pid for infos in self.all_processes.values() for i in infos)
    raise RuntimeError("the raylet did not register")
node.Node.start_ray_processes = once
local_ray.init_local_ray(1)
alive = [p for p in first if psutil.pid_exists(p) and psutil.Process(p).status() != "zombie"]
up = ray.get(ray.remote(lambda: 1).remote())
ray.shutdown()
print(json.dumps({"first": first, "alive": alive, "up": up}))
"""


def test_a_head_that_fails_half_way_leaves_nothing_beside_the_one_that_follows():
    import json
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-c", HALF_STARTED_HEAD], capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr[-2000:]
    result = json.loads(out.stdout.splitlines()[-1])
    assert result["first"]  # the failed head had started its GCS
    assert result["alive"] == []
    assert result["up"] == 1  # the plain head that followed runs tasks


def test_asking_for_the_dashboard_starts_rays_full_head(monkeypatch):
    import ray
    import ray._private.node

    from driver import local_ray
    from driver.cli import build_parser

    plain = ray._private.node.Node
    calls: list[tuple[bool, bool]] = []
    monkeypatch.setattr(
        ray,
        "init",
        lambda **kwargs: calls.append(
            (kwargs["include_dashboard"], ray._private.node.Node is plain)
        ),
    )
    args = build_parser().parse_args(["train", "--dashboard"])
    starting = local_ray.BackgroundRay(2, args.dashboard)
    starting.wait()
    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    starting.shutdown()
    assert calls == [(True, True)]  # Ray's own node, dashboard on
    assert build_parser().parse_args(["train"]).dashboard is False


# Ray's dashboard agent, on the first start only, writes no ports until its raylet is gone:
# as an agent too slow to import on a busy machine, which the raylet waits 15 s for and
# then dies of. In every Python process of the run (sitecustomize), acting in the agent's.
SLOW_FIRST_AGENT = """
import os, time
marker = os.environ.get("UNITY_ROLLOUT_TEST_SLOW_AGENT")
with open("/proc/self/cmdline", "rb") as command:
    agent = b"dashboard/agent.py" in command.read()
if agent and marker and not os.path.exists(marker):
    open(marker, "w").close()
    parent, give_up = os.getppid(), time.monotonic() + 60
    while os.getppid() == parent and time.monotonic() < give_up:
        time.sleep(0.1)  # poll interval: the agent's parent (its raylet) ending
    os._exit(1)
"""
START_AND_RUN = """
import json, ray
from driver import local_ray
local_ray.init_local_ray(1)
up = ray.get(ray.remote(lambda: 1).remote())
ray.shutdown()
print(json.dumps({"up": up}))
"""


def test_a_raylet_that_died_starting_is_started_again_at_once(tmp_path):
    """Ray 2.60's raylet dies when its dashboard agent has not written its ports within
    15 s (seen beside the suite). The lean head notices the death at once, says why, and
    starts again; before, it polled the dead raylet for 3.5 min, then fell back to Ray's
    full head, which the same load can kill the same way."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    (tmp_path / "sitecustomize.py").write_text(SLOW_FIRST_AGENT)
    marker = tmp_path / "slowed"
    root = str(Path(__file__).resolve().parents[2])
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(tmp_path), root]),
        "UNITY_ROLLOUT_TEST_SLOW_AGENT": str(marker),
    }
    out = subprocess.run(
        [sys.executable, "-c", START_AND_RUN], capture_output=True, text=True, env=env, timeout=150
    )  # a safety stop, shorter than the 3.5 min a dead raylet was polled for
    assert out.returncode == 0, out.stderr[-3000:]
    assert marker.exists(), "the first agent was slowed"
    assert json.loads(out.stdout.splitlines()[-1])["up"] == 1  # the second head runs tasks
    said = out.stderr
    assert "Ray's raylet died before it registered (exit" in said, said[-3000:]
    assert "Timed out waiting for file" in said and "metrics_agent_port" in said, said[-3000:]
    assert "starting it again" in said and "full head" not in said, said[-3000:]


# The driver's main thread imports torch and friends while Ray starts on its thread, and
# each of Ray's starts runs Python's fork hooks (its Popen has a preexec_fn): the before
# ones, the fork, the after ones. A module that registers a before/after_in_parent pair in
# between gets only its release run ("release unlocked lock", concurrent.futures.thread's).
# Waiting for that interleaving is luck; what makes it possible is certain: a pair
# registered by the main thread while Ray's thread is starting.
REGISTERED_BESIDE_RAY = """
import os, sys, threading
registered, starting = [], None
real = os.register_at_fork

def spy(**hooks):
    if starting is not None and "before" in hooks:
        registered.append(repr(hooks["before"]))
    return real(**hooks)

os.register_at_fork = spy
from driver import cli  # what `unity-rollout train` has imported when it starts Ray
from driver.local_ray import BackgroundRay
starting = BackgroundRay(1)
import driver.training.train  # the imports that overlap Ray's start
starting.wait()
starting.shutdown()
print(registered)
"""


def test_no_fork_hooks_are_registered_while_ray_starts_beside_the_imports(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    root = str(Path(__file__).resolve().parents[2])
    out = subprocess.run(
        [sys.executable, "-c", REGISTERED_BESIDE_RAY],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": root},
        cwd=tmp_path,
        timeout=240,
    )  # a safety stop
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.strip() == "[]", out.stdout
