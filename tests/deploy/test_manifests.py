"""The deploy manifests, without Kubernetes or machines: they parse, carry the fields KubeRay
and the cluster launcher need, use the Dockerfile's image and the CLI's real commands, turn
token auth on everywhere, and size workers at one Unity instance per CPU."""

from __future__ import annotations

import re
import shlex
import tomllib
from pathlib import Path

import pytest
import yaml

from rollout.cli import build_parser

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
VERSION = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
IMAGE = f"unity-rollout:{VERSION}"
SECRET = {"name": "unity-rollout-ray-auth", "key": "auth_token"}


def load(name: str) -> dict:
    return yaml.safe_load((DEPLOY / name).read_text())


def ray_version() -> str:
    pins = (ROOT / "constraints.txt").read_text()
    return re.search(r"^ray==(\S+)$", pins, re.M)[1]


def cluster_specs() -> list[tuple[str, dict]]:
    return [
        ("raycluster", load("kuberay/raycluster.yaml")["spec"]),
        ("rayjob", load("kuberay/rayjob.yaml")["spec"]["rayClusterSpec"]),
    ]


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


@pytest.mark.parametrize("name, spec", cluster_specs())
def test_kuberay_cluster_spec(name, spec):
    assert spec["rayVersion"] == ray_version()
    head = spec["headGroupSpec"]
    assert head["rayStartParams"]["num-cpus"] == "0"  # no Unity on the head
    assert {p["containerPort"] for p in head["template"]["spec"]["containers"][0]["ports"]} >= {
        6379,
        8265,
    }
    for pod in pod_specs(spec):
        assert pod["securityContext"]["runAsNonRoot"] is True
        assert pod["securityContext"]["runAsUser"] == 1000
        assert any(v.get("emptyDir", {}).get("medium") == "Memory" for v in pod["volumes"])
        for container in pod["containers"]:
            assert container["image"] == IMAGE
            assert_token_env(container)
            assert "command" not in container  # KubeRay supplies `ray start`
    for group in spec["workerGroupSpecs"]:
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


def test_rayjob_embeds_the_raycluster_spec_unchanged():
    assert (
        load("kuberay/rayjob.yaml")["spec"]["rayClusterSpec"]
        == load("kuberay/raycluster.yaml")["spec"]
    )


def test_rayjob_entrypoint_runtime_env_and_submitter():
    job = load("kuberay/rayjob.yaml")
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
        assert "RAY_AUTH_MODE=token ray start" in command
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
