"""The deploy manifests, without Kubernetes or machines: they parse, carry the fields KubeRay
and the cluster launcher need, use the Dockerfile's image and the CLI's real commands, turn
token auth on everywhere, size workers at one Unity instance per CPU, and (the GPU ones) give
the learner, and only the learner, a GPU."""

from __future__ import annotations

import importlib.util
import re
import shlex
import tomllib
from pathlib import Path
from types import SimpleNamespace

import pytest
import ray
import yaml

from driver.cli import build_parser
from driver.local_ray import DASHBOARD_WAIT, GCS_WAIT, START_WAIT_S

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
VERSION = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
IMAGE = f"unity-rollout:{VERSION}"
GPU_IMAGE = f"{IMAGE}-gpu"  # docker build --build-arg TORCH=<a CUDA build>
GPU = "nvidia.com/gpu"
LEARNER_GROUP = "learner-gpu"
SECRET = {"name": "unity-rollout-ray-auth", "key": "auth_token"}
START_WAITS = (GCS_WAIT, DASHBOARD_WAIT)  # what a loaded head needs longer than Ray gives
# (CPU manifest, its GPU-learner twin)
PAIRS = [
    ("kuberay/raycluster.yaml", "kuberay/raycluster-gpu.yaml"),
    ("kuberay/rayjob.yaml", "kuberay/rayjob-gpu.yaml"),
]


def load(name: str) -> dict:
    return yaml.safe_load((DEPLOY / name).read_text())


def ray_version() -> str:
    pins = (ROOT / "constraints.txt").read_text()
    return re.search(r"^ray==(\S+)$", pins, re.M)[1]


def cluster_spec(name: str) -> dict:
    manifest = load(name)
    return manifest["spec"]["rayClusterSpec"] if manifest["kind"] == "RayJob" else manifest["spec"]


def cluster_specs() -> list[tuple[str, dict]]:
    return [(name, cluster_spec(name)) for pair in PAIRS for name in pair]


def gpu_specs() -> list[tuple[str, dict]]:
    return [(gpu, cluster_spec(gpu)) for _, gpu in PAIRS]


def gpus(container: dict) -> dict[str, object]:
    """The container's GPU requests and limits, {"limits": n, "requests": n}, when any."""
    resources = container.get("resources", {})
    return {kind: resources[kind][GPU] for kind in resources if GPU in resources[kind]}


def has_gpu(group: dict) -> bool:
    return any(gpus(c) for c in group["template"]["spec"]["containers"])


def unity_groups(spec: dict) -> list[dict]:
    """The worker groups where rollout workers (and their Unity instances) run."""
    return [group for group in spec["workerGroupSpecs"] if not has_gpu(group)]


def pod_specs(spec: dict) -> list[dict]:
    return [spec["headGroupSpec"]["template"]["spec"]] + [
        group["template"]["spec"] for group in spec["workerGroupSpecs"]
    ]


def assert_token_env(container: dict) -> None:
    env = {item["name"]: item for item in container.get("env", [])}
    assert env["RAY_AUTH_MODE"]["value"] == "token", container["name"]
    assert env["RAY_AUTH_TOKEN"]["valueFrom"]["secretKeyRef"] == SECRET, container["name"]


def parse_cli(command: str) -> object:
    words = shlex.split(command, comments=True)
    assert words[0] == "unity-rollout", command
    return build_parser().parse_args(words[1:])


def test_dockerfile_builds_the_image_the_manifests_use():
    assert f"-t {IMAGE} ." in (ROOT / "Dockerfile").read_text()
    assert f"docker build -t {IMAGE} ." in (DEPLOY / "README.md").read_text()


def torch_builds() -> dict[str, str]:
    """scripts/check-torch-index.py's BUILDS: the values of the image's TORCH build arg."""
    path = ROOT / "scripts/check-torch-index.py"
    spec = importlib.util.spec_from_file_location("check_torch_index", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.BUILDS


def test_dockerfile_and_readme_build_the_gpu_image_the_gpu_manifests_use():
    builds = torch_builds()
    for text in ((ROOT / "Dockerfile").read_text(), (DEPLOY / "README.md").read_text()):
        match = re.search(
            rf"docker build --build-arg TORCH=(\S+) -t {re.escape(GPU_IMAGE)} \.", text
        )
        assert match, f"no `docker build --build-arg TORCH=... -t {GPU_IMAGE} .`"
        assert match[1] in builds and match[1] != "cpu", match[1]  # a CUDA build


@pytest.mark.parametrize("name, spec", cluster_specs())
def test_kuberay_cluster_spec(name, spec):
    assert spec["rayVersion"] == ray_version()
    head = spec["headGroupSpec"]
    assert head["rayStartParams"]["num-cpus"] == "0"  # no Unity on the head
    head_env = {e["name"]: e for e in head["template"]["spec"]["containers"][0]["env"]}
    assert all(head_env[name]["value"] == str(START_WAIT_S) for name in START_WAITS)
    assert {p["containerPort"] for p in head["template"]["spec"]["containers"][0]["ports"]} >= {
        6379,
        8265,
    }
    for pod in pod_specs(spec):
        assert pod["securityContext"]["runAsNonRoot"] is True
        assert pod["securityContext"]["runAsUser"] == 1000
        assert any(v.get("emptyDir", {}).get("medium") == "Memory" for v in pod["volumes"])
        gpu_pod = any(gpus(c) for c in pod["containers"])
        for container in pod["containers"]:
            assert container["image"] == (GPU_IMAGE if gpu_pod else IMAGE)
            assert_token_env(container)
            assert "command" not in container  # KubeRay supplies `ray start`
    assert unity_groups(spec)
    for group in unity_groups(spec):
        container = group["template"]["spec"]["containers"][0]
        cpus = int(group["rayStartParams"]["num-cpus"])
        limits, requests = container["resources"]["limits"], container["resources"]["requests"]
        assert int(limits["cpu"]) == int(requests["cpu"]) == cpus  # one Unity per CPU
        memory_gib = int(limits["memory"].removesuffix("Gi"))
        assert memory_gib >= 2 * cpus and limits["memory"] == requests["memory"]
        assert group["minReplicas"] <= group["replicas"] <= group["maxReplicas"]
        assert group["minReplicas"] < group["maxReplicas"]  # room for the autoscaler
    assert spec["enableInTreeAutoscaling"] is True
    autoscaler = spec["autoscalerOptions"]
    assert autoscaler["upscalingMode"] == "Default" and autoscaler["idleTimeoutSeconds"] > 0
    assert_token_env({"name": "autoscaler", **autoscaler})  # it talks to the GCS too


@pytest.mark.parametrize(
    "job, cluster",
    [
        ("kuberay/rayjob.yaml", "kuberay/raycluster.yaml"),
        ("kuberay/rayjob-gpu.yaml", "kuberay/raycluster-gpu.yaml"),
    ],
)
def test_rayjob_embeds_the_raycluster_spec_unchanged(job, cluster):
    assert load(job)["spec"]["rayClusterSpec"] == load(cluster)["spec"]


@pytest.mark.parametrize("name", ["kuberay/rayjob.yaml", "kuberay/rayjob-gpu.yaml"])
def test_rayjob_entrypoint_runtime_env_and_submitter(name):
    job = load(name)
    assert job["apiVersion"] == "ray.io/v1" and job["kind"] == "RayJob"
    spec = job["spec"]
    args = parse_cli(spec["entrypoint"])
    assert args.command == "train" and args.address == "auto"
    assert args.results_dir == "/workspace/results"  # the head's results volume
    # elastic, asking the autoscaler for every worker CPU its groups can reach; the learner
    # runs on the head, which has no CPUs for Ray
    most = sum(
        int(g["rayStartParams"]["num-cpus"]) * g["maxReplicas"]
        for g in spec["rayClusterSpec"]["workerGroupSpecs"]
    )
    assert args.workers == "auto" and args.max_workers == most and args.learner_cpus == 0
    runtime_env = yaml.safe_load(spec["runtimeEnvYAML"])
    assert set(runtime_env) == {"env_vars"}  # no pip / working_dir: the image holds the pins
    assert all(isinstance(v, str) for v in runtime_env["env_vars"].values())
    submitter = spec["submitterPodTemplate"]["spec"]
    assert submitter["restartPolicy"] == "Never"
    for container in submitter["containers"]:
        assert container["image"] == IMAGE
        assert_token_env(container)
    head_mounts = spec["rayClusterSpec"]["headGroupSpec"]["template"]["spec"]["containers"][0]
    assert {"name": "results", "mountPath": "/workspace/results"} in head_mounts["volumeMounts"]
    volumes = spec["rayClusterSpec"]["headGroupSpec"]["template"]["spec"]["volumes"]
    claim = load("kuberay/results-pvc.yaml")["metadata"]["name"]
    assert {"name": "results", "persistentVolumeClaim": {"claimName": claim}} in volumes


@pytest.mark.parametrize("cpu, gpu", PAIRS)
def test_gpu_manifests_are_the_cpu_ones_plus_the_learner_group(cpu, gpu):
    """Head, Unity workers, autoscaler, token: all as in the CPU manifest (one place to edit
    a setting is the CPU manifest, then its twin)."""
    cpu_spec, gpu_spec = cluster_spec(cpu), cluster_spec(gpu)
    groups = [g for g in gpu_spec["workerGroupSpecs"] if g["groupName"] != LEARNER_GROUP]
    assert len(groups) == len(gpu_spec["workerGroupSpecs"]) - 1
    assert {**gpu_spec, "workerGroupSpecs": groups} == cpu_spec
    assert load(gpu)["metadata"]["name"] == load(cpu)["metadata"]["name"] + "-gpu"
    for pod in pod_specs(cpu_spec):  # the CPU manifests ask no GPU anywhere
        assert not any(gpus(container) for container in pod["containers"])
    if load(cpu)["kind"] == "RayJob":  # its submitter, runtime_env, retries (entrypoint: below)
        outside = ("entrypoint", "rayClusterSpec")
        cpu_rest, gpu_rest = (
            {key: value for key, value in load(name)["spec"].items() if key not in outside}
            for name in (cpu, gpu)
        )
        assert gpu_rest == cpu_rest


def learner_group(spec: dict) -> dict:
    groups = [g for g in spec["workerGroupSpecs"] if has_gpu(g)]
    assert [g["groupName"] for g in groups] == [LEARNER_GROUP], "one group has the GPU"
    return groups[0]


@pytest.mark.parametrize("name, spec", gpu_specs())
def test_the_gpu_is_on_the_learner_group_only(name, spec):
    head = spec["headGroupSpec"]
    assert not any(gpus(c) for c in head["template"]["spec"]["containers"])
    assert "num-gpus" not in head["rayStartParams"]
    group = learner_group(spec)
    (container,) = group["template"]["spec"]["containers"]
    assert gpus(container) == {"limits": 1, "requests": 1}  # extended resources: equal
    assert container["image"] == GPU_IMAGE
    params = group["rayStartParams"]
    assert params["num-gpus"] == "1"  # Ray advertises the pod's GPU
    assert params["num-cpus"] == "0"  # no rollout worker (one CPU each) is placed here
    # always up: `--device cuda` / auto read the cluster's GPUs when the run starts
    assert group["replicas"] == group["minReplicas"] == group["maxReplicas"] == 1
    pod = group["template"]["spec"]
    assert {"key": GPU, "operator": "Exists", "effect": "NoSchedule"} in pod["tolerations"]
    assert any(v.get("emptyDir", {}).get("medium") == "Memory" for v in pod["volumes"])
    limits, requests = container["resources"]["limits"], container["resources"]["requests"]
    assert limits["cpu"] == requests["cpu"] and limits["memory"] == requests["memory"]
    for group in unity_groups(spec):
        assert "num-gpus" not in group["rayStartParams"]


class _RecordedActor:
    """Stands in for ray.remote: keeps the resources an actor class is given."""

    def __init__(self) -> None:
        self.resources: dict[str, float] = {}

    def __call__(self, *args: object, **kwargs: object) -> object:
        return lambda cls: self

    def options(self, **options: float) -> _RecordedActor:
        self.resources.update(options)
        return self

    def remote(self, *args: object, **kwargs: object) -> object:
        return SimpleNamespace(prepare=SimpleNamespace(remote=lambda: None))


def ray_nodes(spec: dict) -> dict[str, dict[str, float]]:
    """What each group's Ray node offers, from its rayStartParams."""
    groups = [("head", spec["headGroupSpec"])] + [
        (g["groupName"], g) for g in spec["workerGroupSpecs"]
    ]
    return {
        name: {
            "CPU": float(group["rayStartParams"]["num-cpus"]),
            "GPU": float(group["rayStartParams"].get("num-gpus", 0)),
        }
        for name, group in groups
    }


@pytest.mark.parametrize("name, spec", gpu_specs())
def test_the_learner_actor_fits_the_gpu_group_and_rollout_workers_do_not(name, spec, monkeypatch):
    """The learner's real Ray options under --device cuda (learners.host.remote) against what
    each group's node offers: only the GPU group can take the learner, and only the Unity
    groups can take a rollout worker (one CPU, no GPU: driver.training.train on a cluster)."""
    from learners.host.remote import learner_actor

    recorded = _RecordedActor()
    monkeypatch.setattr(ray, "remote", recorded)
    learner_actor(None, device="cuda")
    learner = {
        "CPU": float(recorded.resources.get("num_cpus", 1)),
        "GPU": float(recorded.resources.get("num_gpus", 0)),
    }
    assert learner["GPU"] == 1, recorded.resources
    worker = {"CPU": 1.0, "GPU": 0.0}

    def fits(demand: dict[str, float]) -> set[str]:
        return {
            node
            for node, offer in ray_nodes(spec).items()
            if all(offer[key] >= amount for key, amount in demand.items())
        }

    assert fits(learner) == {LEARNER_GROUP}
    assert fits(worker) == {g["groupName"] for g in unity_groups(spec)}


def test_gpu_rayjob_entrypoint_is_the_cpu_one_with_device_cuda():
    cpu = parse_cli(load("kuberay/rayjob.yaml")["spec"]["entrypoint"])
    gpu = parse_cli(load("kuberay/rayjob-gpu.yaml")["spec"]["entrypoint"])
    assert gpu.device == "cuda"  # no GPU in the cluster: one line before any worker starts
    assert cpu.device != "cuda"
    assert gpu.run_id != cpu.run_id  # both runs can share the results volume
    ignored = {"device", "run_id", "given"}  # given: which flags the command line had
    assert {k: v for k, v in vars(gpu).items() if k not in ignored} == {
        k: v for k, v in vars(cpu).items() if k not in ignored
    }
    assert gpu.learner_cpus == 0  # the learner asks no CPU: the GPU group offers Ray none


def test_auth_secret_template_holds_no_real_token():
    secret = load("kuberay/auth-secret.yaml")
    assert secret["kind"] == "Secret" and secret["metadata"]["name"] == SECRET["name"]
    token = secret["stringData"][SECRET["key"]]
    assert token.startswith("REPLACE") and not re.fullmatch(r"[0-9a-f]{32,}", token)


def test_cluster_launcher_config():
    config = load("ray-cluster.yaml")
    for key in ("cluster_name", "provider", "auth", "docker", "head_node_type"):
        assert key in config
    assert config["docker"]["image"] == IMAGE
    run_options = " ".join(config["docker"]["run_options"])
    assert "--env RAY_AUTH_MODE=token" in run_options and "--shm-size" in run_options
    assert ":/builds" in run_options and ":/workspace/results" in run_options
    assert config["file_mounts"]["~/.ray/auth_token"] == "~/.ray/auth_token"
    assert config["head_node_type"] in config["available_node_types"]
    head, workers = config["head_start_ray_commands"], config["worker_start_ray_commands"]
    for command in head + workers:
        assert "RAY_AUTH_MODE=token " in command and " ray start " in command
    assert all(f"{name}={START_WAIT_S} " in c for c in head for name in START_WAITS)
    assert any("--head" in c and "--dashboard-host=127.0.0.1" in c for c in head)
    assert any("--num-cpus=0" in c for c in head)  # the head runs no Unity
    assert all("--address=$RAY_HEAD_IP:6379" in c for c in workers)


def readme_commands(text: str) -> list[str]:
    """Each `unity-rollout train|collect ...` of the page's code blocks, continuations joined."""
    commands, lines = [], text.splitlines()
    for index, line in enumerate(lines):
        match = re.search(r"unity-rollout (train|collect)\b.*", line)
        if not match or "`" in match[0]:
            continue
        command = match[0]
        while command.endswith("\\"):
            index += 1
            command = command[:-1] + " " + lines[index].strip()
        commands.append(command)
    return commands


def test_readme_commands_parse_with_the_cli():
    commands = readme_commands((DEPLOY / "README.md").read_text())
    assert len(commands) >= 4
    for command in commands:
        args = parse_cli(command.replace('"$PWD/results"', "results"))
        assert args.command in ("train", "collect")
        if "--address" in command:
            assert args.address == "auto", command  # the job driver joins its cluster
