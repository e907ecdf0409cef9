"""ONNX export in the ML-Agents layout (no Ray): names, constants, dynamic batch, and the
deterministic outputs of onnxruntime against the torch policy, normalization included."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from mlagents_envs.base_env import ActionSpec, BehaviorSpec, ObservationSpec

from driver import cli
from learners.acting.numpy_policy import ACTION_CLIP, is_entities
from learners.host import checkpoint
from learners.host.checkpoint import network_settings_dict, spec_to_dict
from learners.host.export import export_checkpoint, export_onnx
from learners.networks.policies import ActorCritic
from learners.trainer_config.keys import VIS_ENCODE_TYPES
from learners.trainer_config.settings import NetworkSettings
from testkit.segments import BUFFER, GRID, IMAGE, VECTOR

SPECS = {
    "continuous": BehaviorSpec([VECTOR], ActionSpec(2, ())),  # 3DBall-like
    "discrete": BehaviorSpec([VECTOR], ActionSpec(0, (3, 4, 2))),
    "hybrid": BehaviorSpec([VECTOR, GRID], ActionSpec(2, (3, 2))),
    "image": BehaviorSpec([IMAGE, VECTOR], ActionSpec(1, (4,))),
    "entities": BehaviorSpec([VECTOR, BUFFER], ActionSpec(0, (3, 3, 3))),  # Sorter-like
}
SETTINGS = NetworkSettings(hidden_units=32, num_layers=2, normalize=True)
CAMERA = ObservationSpec((3, 40, 40), IMAGE.dimension_property, IMAGE.observation_type, "cam")


def observations(spec: BehaviorSpec, n: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Random observations; a variable-length sensor's rows padded with zeros after a
    random count of entities (none included), as Unity pads them."""
    rng = np.random.default_rng(seed)
    obs = {
        o.name: (rng.normal(size=(n, *o.shape)) * 3 + 2).astype(np.float32)
        for o in spec.observation_specs
    }
    for o in spec.observation_specs:
        if is_entities(o):
            present = rng.integers(0, o.shape[0] + 1, n)
            obs[o.name][np.arange(o.shape[0]) >= present[:, None]] = 0.0
    return obs


def build_network(
    spec: BehaviorSpec, seed: int = 0, settings: NetworkSettings = SETTINGS
) -> ActorCritic:
    """Heads with large weights (so clipping and argmax matter) and shifted statistics."""
    torch.manual_seed(seed)
    network = ActorCritic(spec, settings)
    with torch.no_grad():
        for head in (network.mean, network.logits):
            if head is not None:
                torch.nn.init.normal_(head.weight, std=1.0)
                torch.nn.init.normal_(head.bias, std=0.5)
        if network.log_std is not None:
            network.log_std.fill_(math.log(0.1))
    network.update_normalization(
        {k: torch.from_numpy(v) for k, v in observations(spec, 256, seed=99).items()}
    )
    return network


def masks(spec: BehaviorSpec, n: int, seed: int = 0) -> np.ndarray:
    """Random masks (True = allowed) with at least one allowed action per branch."""
    rng = np.random.default_rng(seed)
    parts = []
    for size in spec.action_spec.discrete_branches:
        part = rng.random((n, size)) < 0.6
        part[np.arange(n), rng.integers(0, size, n)] = True
        parts.append(part)
    return np.concatenate(parts, axis=1)


def feeds(spec: BehaviorSpec, obs: dict[str, np.ndarray], mask: np.ndarray | None) -> dict:
    feed = {f"obs_{i}": obs[o.name] for i, o in enumerate(spec.observation_specs)}
    if spec.action_spec.discrete_branches:
        assert mask is not None
        feed["action_masks"] = mask.astype(np.float32)  # ML-Agents: 1.0 = allowed
    return feed


def session(path: Path) -> ort.InferenceSession:
    options = ort.SessionOptions()
    options.intra_op_num_threads = options.inter_op_num_threads = 1
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def run(sess: ort.InferenceSession, feed: dict) -> dict[str, np.ndarray]:
    return dict(zip([o.name for o in sess.get_outputs()], sess.run(None, feed), strict=True))


def torch_deterministic(
    network: ActorCritic, obs: dict[str, np.ndarray], mask: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    tensors = {k: torch.from_numpy(v) for k, v in obs.items()}
    torch_mask = torch.from_numpy(mask) if mask is not None else None
    continuous, discrete, _ = network.act(tensors, torch_mask, deterministic=True)
    return network.unity_action(continuous).numpy(), discrete.numpy()


@pytest.mark.parametrize("kind", list(SPECS))
def test_exported_graph_matches_the_policy(tmp_path, kind):
    spec = SPECS[kind]
    network = build_network(spec)
    path = export_onnx(network, tmp_path / f"{kind}.onnx")
    model = onnx.load(str(path))
    onnx.checker.check_model(model, full_check=True)

    has_continuous = spec.action_spec.continuous_size > 0
    branches = list(spec.action_spec.discrete_branches)
    expected_inputs = [f"obs_{i}" for i in range(len(spec.observation_specs))]
    expected_outputs = ["version_number", "memory_size"]
    if has_continuous:
        expected_outputs += [
            "continuous_actions",
            "continuous_action_output_shape",
            "deterministic_continuous_actions",
        ]
    if branches:
        expected_inputs.append("action_masks")
        expected_outputs += [
            "discrete_actions",
            "discrete_action_output_shape",
            "deterministic_discrete_actions",
        ]
    assert [i.name for i in model.graph.input] == expected_inputs
    assert [o.name for o in model.graph.output] == expected_outputs
    for value, obs_spec in zip(model.graph.input, spec.observation_specs, strict=False):
        dims = [d.dim_param or d.dim_value for d in value.type.tensor_type.shape.dim]
        assert dims == ["batch", *obs_spec.shape]  # images NCHW, as the spec (C, H, W)
        assert value.type.tensor_type.elem_type == onnx.TensorProto.FLOAT

    sess = session(path)
    for n in (1, 7):
        obs = observations(spec, n, seed=n)
        mask = masks(spec, n, seed=n) if branches else None
        out = run(sess, feeds(spec, obs, mask))
        np.testing.assert_array_equal(out["version_number"], np.array([3.0], np.float32))
        np.testing.assert_array_equal(out["memory_size"], np.array([0.0], np.float32))
        assert out["version_number"].dtype == out["memory_size"].dtype == np.float32
        continuous, discrete = torch_deterministic(network, obs, mask)
        if has_continuous:
            size = spec.action_spec.continuous_size
            np.testing.assert_array_equal(out["continuous_action_output_shape"], [float(size)])
            assert out["continuous_actions"].shape == (n, size)
            assert out["continuous_actions"].dtype == np.float32
            assert np.abs(out["continuous_actions"]).max() <= 1.0
            np.testing.assert_allclose(
                out["deterministic_continuous_actions"], continuous, rtol=0, atol=1e-5
            )
        if branches:
            np.testing.assert_array_equal(out["discrete_action_output_shape"], [branches])
            assert out["discrete_action_output_shape"].dtype == np.float32
            assert out["discrete_actions"].shape == (n, len(branches))
            assert out["deterministic_discrete_actions"].dtype == np.int64
            np.testing.assert_array_equal(out["deterministic_discrete_actions"], discrete)

    # The comparison is sensitive to normalization: without it the actions differ.
    plain = build_network(spec)
    for encoder in plain.encoders:
        if encoder.norm is not None:
            encoder.norm.mean.zero_()
            encoder.norm.var.fill_(1.0)
    obs = observations(spec, 64, seed=5)
    mask = masks(spec, 64, seed=5) if branches else None
    changed_c, changed_d = torch_deterministic(plain, obs, mask)
    real_c, real_d = torch_deterministic(network, obs, mask)
    assert np.abs(changed_c - real_c).max(initial=0) > 1e-3 or (changed_d != real_d).any()


@pytest.mark.parametrize("kind", ["continuous", "discrete", "hybrid"])
def test_stochastic_outputs_respect_masks_and_spread(tmp_path, kind):
    spec = SPECS[kind]
    network = build_network(spec, seed=3)
    if network.mean is not None:  # means inside (-1, 1), so samples spread around them
        torch.nn.init.normal_(network.mean.weight.data, std=0.05)
        network.mean.bias.data.zero_()
    sess = session(export_onnx(network, tmp_path / "policy.onnx"))
    n = 4000
    obs = {k: np.repeat(v, n, axis=0) for k, v in observations(spec, 1, seed=4).items()}
    mask = masks(spec, n, seed=4) if spec.action_spec.discrete_branches else None
    out = run(sess, feeds(spec, obs, mask))
    offset = 0
    for branch, size in enumerate(spec.action_spec.discrete_branches):
        assert mask is not None
        chosen = out["discrete_actions"][:, branch]
        assert ((chosen >= 0) & (chosen < size)).all()
        assert mask[np.arange(n), offset + chosen].all(), "a masked action was sampled"
        assert len(np.unique(chosen)) > 1  # sampled, not the argmax
        offset += size
    if spec.action_spec.continuous_size:
        samples = out["continuous_actions"]
        deterministic = out["deterministic_continuous_actions"][0]
        assert np.abs(deterministic).max() < 0.2  # away from the clip: sample mean ~ mean
        # Unity gets clamp(a, -3, 3) / 3, as from mlagents-learn: std exp(log_std) / 3
        np.testing.assert_allclose(samples.std(0), 0.1 / ACTION_CLIP, rtol=0.1)
        np.testing.assert_allclose(samples.mean(0), deterministic, rtol=0, atol=0.02)


def write_checkpoint(run_dir: Path) -> tuple[Path, dict[str, ActorCritic]]:
    networks = {
        "3DBall?team=0": build_network(SPECS["continuous"], seed=1),
        "Grid?team=0": build_network(SPECS["image"], seed=2),
    }
    behaviors = {
        name: {
            "spec": spec_to_dict(net.spec),
            "network_settings": network_settings_dict(SETTINGS),
            "network": net.state_dict(),
            "algorithm": {},
        }
        for name, net in networks.items()
    }
    path = checkpoint.save(
        run_dir / "checkpoints" / "step_100.pt",
        {"step": 100, "version": 3, "meta": {}, "behaviors": behaviors},
    )
    return path, networks


def test_export_checkpoint_writes_one_file_per_behavior(tmp_path):
    run_dir = tmp_path / "run"
    path, networks = write_checkpoint(run_dir)
    written = export_checkpoint(run_dir)
    exported = run_dir / "exported"
    assert sorted(written) == sorted(
        [exported / "3DBall_team=0.onnx", exported / "Grid_team=0.onnx"]
    )
    for name, network in networks.items():
        spec = network.spec
        obs = observations(spec, 5, seed=8)
        mask = masks(spec, 5, seed=8) if spec.action_spec.discrete_branches else None
        out = run(session(exported / f"{name.replace('?', '_')}.onnx"), feeds(spec, obs, mask))
        continuous, discrete = torch_deterministic(network, obs, mask)
        np.testing.assert_allclose(
            out["deterministic_continuous_actions"], continuous, rtol=0, atol=1e-5
        )
        if mask is not None:
            np.testing.assert_array_equal(out["deterministic_discrete_actions"], discrete)
    elsewhere = export_checkpoint(path, tmp_path / "out")
    assert sorted(p.name for p in elsewhere) == ["3DBall_team=0.onnx", "Grid_team=0.onnx"]
    assert all(p.parent == tmp_path / "out" for p in elsewhere)


@pytest.mark.parametrize("kind", VIS_ENCODE_TYPES)
def test_every_visual_encoder_exports_and_round_trips_a_checkpoint(tmp_path, kind):
    """A 40x40 camera (above every type's minimum) through each encoder: the checkpoint
    keeps the type, and onnxruntime acts as torch does."""
    spec = BehaviorSpec([CAMERA, VECTOR], ActionSpec(1, (4,)))
    settings = NetworkSettings(hidden_units=32, num_layers=1, vis_encode_type=kind)
    network = build_network(spec, seed=4, settings=settings)
    entry = {
        "spec": spec_to_dict(spec),
        "network_settings": network_settings_dict(settings),
        "network": network.state_dict(),
        "algorithm": {},
    }
    state = {"step": 1, "version": 1, "meta": {}, "behaviors": {"Cam?team=0": entry}}
    path = checkpoint.save(tmp_path / "checkpoints" / "step_1.pt", state)
    rebuilt = checkpoint.networks(checkpoint.load(path))["Cam?team=0"]
    assert rebuilt.settings == settings and rebuilt.settings.vis_encode_type == kind
    assert all(torch.equal(v, rebuilt.state_dict()[k]) for k, v in network.state_dict().items())
    (exported,) = export_checkpoint(path, tmp_path / "onnx")
    model = onnx.load(str(exported))
    dims = [d.dim_param or d.dim_value for d in model.graph.input[0].type.tensor_type.shape.dim]
    assert dims == ["batch", 3, 40, 40]
    sess = session(exported)
    for n in (1, 6):
        obs = observations(spec, n, seed=n)
        obs["cam"] = np.random.default_rng(n).random((n, 3, 40, 40), dtype=np.float32)
        mask = masks(spec, n, seed=n)
        out = run(sess, feeds(spec, obs, mask))
        continuous, discrete = torch_deterministic(network, obs, mask)
        np.testing.assert_allclose(
            out["deterministic_continuous_actions"], continuous, rtol=0, atol=1e-5
        )
        np.testing.assert_array_equal(out["deterministic_discrete_actions"], discrete)
    # the comparison sees the image: other pixels move the actions well past the tolerance
    obs["cam"] = np.random.default_rng(99).random((6, 3, 40, 40), dtype=np.float32)
    assert np.abs(torch_deterministic(network, obs, mask)[0] - continuous).max() > 1e-3


def test_cli_export(tmp_path, capsys):
    path, _ = write_checkpoint(tmp_path / "run")
    assert cli.main(["export", str(path), "--out", str(tmp_path / "onnx")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert sorted(Path(line) for line in lines) == sorted(
        [tmp_path / "onnx" / "3DBall_team=0.onnx", tmp_path / "onnx" / "Grid_team=0.onnx"]
    )
    assert all(Path(line).is_file() for line in lines)


@pytest.mark.parametrize("bad", ["missing.pt", "empty_dir", "garbage.pt"])
def test_cli_export_bad_source(tmp_path, capsys, bad):
    (tmp_path / "empty_dir").mkdir()
    (tmp_path / "garbage.pt").write_text("not a checkpoint\n")
    assert cli.main(["export", str(tmp_path / bad)]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert len(captured.err.strip().splitlines()) == 1
    assert captured.err.startswith("error:")


def test_squashed_conditional_policy_exports_tanh_of_the_mean(tmp_path):
    """SAC networks: the deterministic action is tanh(mean), samples are tanh of a Gaussian
    whose spread comes from the state-dependent log-std head."""
    spec = SPECS["continuous"]
    torch.manual_seed(0)
    settings = NetworkSettings(32, 2, normalize=True, tanh_squash=True, conditional_sigma=True)
    network = ActorCritic(spec, settings)
    with torch.no_grad():
        torch.nn.init.normal_(network.mean.weight, std=0.3)
        network.log_std_head.bias.fill_(math.log(0.1))
    network.update_normalization(
        {k: torch.from_numpy(v) for k, v in observations(spec, 256, seed=99).items()}
    )
    sess = session(export_onnx(network, tmp_path / "sac.onnx"))
    obs = observations(spec, 7, seed=1)
    out = run(sess, feeds(spec, obs, None))
    expected, _ = torch_deterministic(network, obs, None)
    with torch.no_grad():
        hidden = network.features({k: torch.from_numpy(v) for k, v in obs.items()})
        mean, _ = network.mean_log_std(hidden)
    np.testing.assert_allclose(expected, torch.tanh(mean).numpy(), rtol=0, atol=1e-6)
    np.testing.assert_allclose(out["deterministic_continuous_actions"], expected, atol=1e-5)
    assert np.abs(out["deterministic_continuous_actions"]).max() > 0.1  # not all ~0

    n = 4000  # stochastic: tanh of N(mean, 0.1), so atanh of the samples has that spread
    many = {k: np.repeat(v[:1], n, axis=0) for k, v in obs.items()}
    samples = run(sess, feeds(spec, many, None))["continuous_actions"]
    assert np.abs(samples).max() < 1.0
    pre = np.arctanh(samples.astype(np.float64))
    np.testing.assert_allclose(pre.std(0), 0.1, rtol=0.1)
    np.testing.assert_allclose(pre.mean(0), mean[0].numpy(), atol=0.02)
