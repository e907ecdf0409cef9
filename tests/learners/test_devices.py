"""The learner's device plumbing, as far as it goes on a machine without a GPU (the mixed
precision tests also run on CUDA where there is one).

A CUDA run cannot happen here, so the update paths are run with torch's default device set
to ``meta``: every tensor the learner creates without naming a device then lands on
``meta``, and the first operation mixing it with the network's tensors fails. That is the
bug a GPU learner would hit (a tensor left on the CPU), found on the CPU.
"""

from __future__ import annotations

import pytest
import torch
from mlagents_envs.base_env import ActionSpec, BehaviorSpec

from batches import keys
from learners.host import devices
from learners.host.devices import Compute, DeviceError, check_device, learner_device, to_cpu
from learners.host.learner import CentralLearner
from learners.trainer_config.parse import ConfigError, parse_config
from testkit.segments import DEVICES, IMAGE, VECTOR, compute_of, segment


def test_device_names_are_checked_in_one_line():
    for good in ("auto", "cpu", "cuda", "cuda:1"):
        assert check_device(good) == good
    for bad in ("gpu", "cuda:", "CUDA", "cuda:x", 3):
        with pytest.raises(DeviceError, match=r"^--device: .* use auto, cpu, cuda or cuda:N$"):
            check_device(bad)


def test_the_driver_asks_a_gpu_only_where_one_is_and_refuses_cuda_without_one():
    assert learner_device("auto", 0) == "cpu"
    assert learner_device("auto", 2) == "auto"  # resolved in the actor, on Ray's GPU
    assert learner_device("cpu", 4) == "cpu"
    assert learner_device("cuda:0", 1) == "cuda:0"
    with pytest.raises(DeviceError) as error:
        learner_device("cuda", 0)
    message = str(error.value)
    assert "\n" not in message and "no GPU" in message and "--device cpu" in message


def test_the_learner_process_resolves_its_device():
    gpus = torch.cuda.device_count()
    assert Compute.of("cpu") == Compute("cpu")
    assert Compute.of("auto").device == ("cuda" if gpus else "cpu")
    with pytest.raises(DeviceError, match=f"sees {gpus} CUDA device"):
        Compute.of(f"cuda:{gpus}")  # one past the last


def test_mixed_precision_falls_back_to_float32_with_a_note_where_bfloat16_is_emulated(
    monkeypatch,
):
    """Emulated bfloat16 made an update 13 times slower on an AVX2 CPU: the learner
    computes in float32 and says why in one line; where bfloat16 is native it keeps it."""
    monkeypatch.setattr(devices, "bfloat16_slow", lambda device: f"{device} emulates it")
    compute = Compute.of("cpu", mixed_precision=True)
    assert (compute.device, compute.mixed_precision) == ("cpu", False)
    assert compute.note is not None and "\n" not in compute.note
    assert (
        compute.note.startswith("--mixed-precision: cpu emulates it") and "float32" in compute.note
    )
    learner = CentralLearner(parse_config({}), compute=compute)
    assert learner.progress()["notes"] == [compute.note]  # how the driver hears of it
    assert Compute.of("cpu") == Compute("cpu")  # not asked: nothing to say
    monkeypatch.setattr(devices, "bfloat16_slow", lambda device: None)
    assert Compute.of("cpu", mixed_precision=True) == Compute("cpu", True)
    assert CentralLearner(parse_config({})).progress()["notes"] == []


def test_the_bfloat16_probe_answers_in_one_line():
    why = devices.bfloat16_slow(torch.device("cpu"))
    native = torch.ops.mkldnn._is_mkldnn_bf16_supported()
    assert (why is None) == native, why  # torch's own test of oneDNN's bfloat16
    assert why is None or ("\n" not in why and torch.backends.cpu.get_cpu_capability() in why)


def test_torch_settings_device_is_mlagents_key_and_checked():
    assert parse_config({"torch_settings": {"device": "cuda:0"}}).torch_device == "cuda:0"
    assert parse_config({"torch_settings": {"device": None}}).torch_device is None
    assert parse_config({}).torch_device is None
    with pytest.raises(ConfigError, match=r"^torch_settings.device: 'tpu' is not a device"):
        parse_config({"torch_settings": {"device": "tpu"}})
    with pytest.raises(ConfigError, match="torch_settings"):
        parse_config({"torch_settings": {"devise": "cpu"}})


def behaviors() -> list[tuple[str, BehaviorSpec]]:
    return [
        ("ppo", BehaviorSpec([VECTOR], ActionSpec(2, (3,)))),
        ("ppo", BehaviorSpec([IMAGE, VECTOR], ActionSpec(0, (3, 3)))),
        ("impala", BehaviorSpec([VECTOR], ActionSpec(2, ()))),
        ("sac", BehaviorSpec([VECTOR], ActionSpec(2, ()))),
        ("sac", BehaviorSpec([IMAGE], ActionSpec(0, (4,)))),
    ]


@pytest.mark.parametrize(("trainer", "spec"), behaviors())
def test_every_update_creates_its_tensors_on_the_networks_device(trainer, spec):
    hyper = {"batch_size": 16, "buffer_size": 48}
    if trainer == "sac":
        hyper |= {"buffer_init_steps": 0, "steps_per_update": 8}
    config = parse_config({"behaviors": {"B": {"trainer_type": trainer, "hyperparameters": hyper}}})
    learner = CentralLearner(config, compute=Compute("cpu"))
    learner.submit([segment(spec, 1, 4, behavior="B?team=0")])  # builds the network, on cpu
    data = segment(spec, 4, 16, behavior="B?team=0", seed=1)
    before = learner.version
    with torch.device("meta"):  # a tensor made without a device would land here
        learner.submit([data])
    assert learner.version > before  # an update ran, every tensor on the network's device
    state = learner.state_dict()
    assert all(t.device.type == "cpu" for t in state["behaviors"]["B?team=0"]["network"].values())


def test_weights_are_copied_once_per_version():
    spec = BehaviorSpec([VECTOR], ActionSpec(2, ()))
    config = parse_config(
        {"behaviors": {"B": {"hyperparameters": {"buffer_size": 32, "batch_size": 16}}}}
    )
    learner = CentralLearner(config)
    learner.submit([segment(spec, 1, 8, behavior="B?team=0")])
    version, first = learner.weights()
    assert learner.weights()[1] is first  # the same copy for every worker that asks
    learner.submit([segment(spec, 2, 16, behavior="B?team=0", seed=2)])  # an update
    newer, second = learner.weights()
    assert newer == version + 1 and second is not first
    changed = [
        k for k in first["B?team=0"] if (first["B?team=0"][k] != second["B?team=0"][k]).any()
    ]
    assert changed  # the new copy holds the new weights


def test_to_cpu_keeps_the_structure():
    state = {"a": torch.ones(2), "b": [torch.zeros(1), (3, "x")], "c": {"d": torch.tensor(1)}}
    moved = to_cpu(state)
    assert moved["b"][1] == (3, "x") and torch.equal(moved["c"]["d"], torch.tensor(1))


def test_uint8_images_train_like_their_float_form():
    """Segments carry PNG cameras as uint8 0..255; the learner's encoder reads them as
    the float k/255 a worker acted on: the same losses from either form."""
    spec = BehaviorSpec([IMAGE, VECTOR], ActionSpec(0, (3,)))
    config = parse_config(
        {"behaviors": {"B": {"hyperparameters": {"buffer_size": 16, "batch_size": 16}}}}
    )
    data = segment(spec, 2, 16, behavior="B?team=0", seed=3)
    pixels = torch.randint(0, 256, data[keys.OBS, "camera"].shape).float()
    reports = []
    for form in (pixels.to(torch.uint8), pixels / 255):
        batch = data.clone()
        for key in ((keys.OBS, "camera"), (keys.NEXT, keys.OBS, "camera")):
            batch.set(key, form, inplace=False)
        torch.manual_seed(0)
        learner = CentralLearner(config, seed=5)
        learner.submit([batch])
        reports.append(learner.drain_reports()[0][2])
    assert reports[0]["Losses/Value Loss"] == pytest.approx(reports[1]["Losses/Value Loss"])
    assert reports[0]["Losses/Policy Loss"] == pytest.approx(reports[1]["Losses/Policy Loss"])


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("mixed", [False, True])
def test_mixed_precision_runs_the_hidden_layers_in_bfloat16_and_the_heads_in_float32(mixed, device):
    spec = BehaviorSpec([IMAGE, VECTOR], ActionSpec(0, (3,)))
    config = parse_config(
        {"behaviors": {"B": {"hyperparameters": {"buffer_size": 16, "batch_size": 16}}}}
    )
    learner = CentralLearner(config, compute=compute_of(device, mixed))
    learner.submit([segment(spec, 1, 1, behavior="B?team=0")])
    network = learner.behaviors["B?team=0"].network
    seen: dict[str, set[torch.dtype]] = {"conv": set(), "trunk": set(), "critic": set()}
    seen |= {"trunk out": set(), "logits in": set(), "value in": set(), "value out": set()}
    conv = next(m for m in network.encoders[0].modules() if isinstance(m, torch.nn.Conv2d))
    conv.register_forward_hook(lambda m, i, o: seen["conv"].add(o.dtype))
    network.trunk[0].register_forward_hook(lambda m, i, o: seen["trunk"].add(o.dtype))
    network.critic_trunk[0].register_forward_hook(lambda m, i, o: seen["critic"].add(o.dtype))
    network.trunk.register_forward_hook(lambda m, i, o: seen["trunk out"].add(o.dtype))
    network.logits.register_forward_pre_hook(lambda m, i: seen["logits in"].add(i[0].dtype))
    network.value.register_forward_pre_hook(lambda m, i: seen["value in"].add(i[0].dtype))
    network.value.register_forward_hook(lambda m, i, o: seen["value out"].add(o.dtype))
    learner.submit([segment(spec, 2, 16, behavior="B?team=0", seed=4)])
    report = learner.drain_reports()[0][2]
    # the gradient passes and GAE's value pass (where CUDA autocast once met torchrl's vmap
    # and crashed) in bfloat16, the heads after them in float32
    hidden = {torch.bfloat16} if mixed else {torch.float32}
    assert seen["conv"] == seen["trunk"] == seen["critic"] == hidden
    for where in ("trunk out", "logits in", "value in", "value out"):
        assert seen[where] == {torch.float32}, where
    assert all(torch.isfinite(torch.tensor(v)) for v in report.values())
    for parameter in network.parameters():  # weights and their gradients stay float32
        assert parameter.dtype == torch.float32
        assert parameter.grad is None or parameter.grad.dtype == torch.float32


@pytest.mark.parametrize("encoder", ["simple", "nature_cnn", "resnet", "match3", "fully_connected"])
@pytest.mark.parametrize(
    ("trainer", "actions"), [("ppo", (0, (3,))), ("impala", (0, (3,))), ("sac", (2, ()))]
)
@pytest.mark.parametrize("device", DEVICES)
def test_mixed_precision_updates_every_trainer_and_encoder(trainer, actions, encoder, device):
    """bfloat16 autocast through every trainer's whole update, value estimates included,
    for each of ML-Agents' image encoders."""
    from mlagents_envs.base_env import DimensionProperty, ObservationSpec
    from mlagents_envs.base_env import ObservationType as Obs

    pixels = (DimensionProperty.NONE, *(DimensionProperty.TRANSLATIONAL_EQUIVARIANCE,) * 2)
    from learners.networks.encoders import MIN_SIZE

    side = MIN_SIZE[encoder]  # the smallest image each encoder takes: the cheapest update
    camera = ObservationSpec((3, side, side), pixels, Obs.DEFAULT, "camera")
    spec = BehaviorSpec([camera, VECTOR], ActionSpec(*actions))
    hyper = {"batch_size": 8, "buffer_size": 16, "num_epoch": 1}
    if trainer == "sac":
        hyper = {"batch_size": 8, "buffer_init_steps": 0, "steps_per_update": 8}
    network = {"vis_encode_type": encoder, "hidden_units": 16}
    behavior = {"trainer_type": trainer, "hyperparameters": hyper, "network_settings": network}
    config = parse_config({"behaviors": {"B": behavior}})
    learner = CentralLearner(config, compute=compute_of(device, True))
    learner.submit([segment(spec, 2, 9, behavior="B?team=0", seed=2)])
    reports = learner.drain_reports()
    assert reports, "no update ran"
    assert all(torch.isfinite(torch.tensor(v)) for v in reports[-1][2].values())


def test_usable_cores_are_the_affinity_within_the_containers_cpu_quota(tmp_path):
    """As mlagents-learn's cpu_utils: a pod limited to 2 CPUs on a big node takes 2."""
    import os

    from learners.host.devices import usable_cores

    affinity = len(os.sched_getaffinity(0))
    assert usable_cores(tmp_path) == affinity  # no cgroup files: the affinity
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert usable_cores(tmp_path) == affinity  # v2 without a quota
    (tmp_path / "cpu.max").write_text("150000 100000\n")
    assert usable_cores(tmp_path) == min(affinity, 2)  # 1.5 CPUs: two threads
    (tmp_path / "cpu.max").write_text("50000 100000\n")
    assert usable_cores(tmp_path) == 1
    (tmp_path / "cpu.max").unlink()
    (tmp_path / "cpu").mkdir()
    (tmp_path / "cpu" / "cpu.cfs_quota_us").write_text("-1\n")  # v1 without a quota
    (tmp_path / "cpu" / "cpu.cfs_period_us").write_text("100000\n")
    assert usable_cores(tmp_path) == affinity
    (tmp_path / "cpu" / "cpu.cfs_quota_us").write_text("100000\n")
    assert usable_cores(tmp_path) == 1
    assert usable_cores() >= 1  # this machine's own cgroup
