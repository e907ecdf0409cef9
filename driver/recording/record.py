"""``unity-rollout record-demo``: one Unity instance, a trained policy (or a unitysim
environment's scripted expert) acting, every step of one behavior written to a ``.demo``
file as Unity's ``DemonstrationRecorder`` writes it (``demonstrations.write_demo``).

Everything the user can get wrong is checked before the build starts where it can be (the
checkpoint, the output's folder) and right after its handshake otherwise (the behavior, the
specs), and is a :class:`TrainingError` or ``UnityError`` of one line. The file is written
to a temporary name beside the output and renamed into place, so a failure or an
interruption never leaves a partial ``.demo`` behind the name.
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mlagents_envs.base_env import BehaviorSpec

from batches.contracts import base_name
from demonstrations import DemoError, Demonstration, spec_mismatch, write_demo
from driver.declaration import TrainingError
from driver.options import RecordDemoOptions
from driver.recording.recorder import ExpertActor, PolicyActor, RandomActor, StepActor, StepRecorder
from driver.system import record_unity_config
from rollout.environment.unity import UnityInstance
from unitysim.experts import EXPERTS, expert_for

NAME_LENGTH = 16  # Unity's DemonstrationRecorder.MaxNameLength
NO_AGENT_STEPS = 3000  # exchanges without one agent of the behavior before giving up


@dataclass(frozen=True)
class Recorded:
    path: Path
    behavior: str
    steps: int
    episodes: int
    mean_reward: float


def demo_name(path: Path) -> str:
    """The demo's name as Unity makes it from the recorder's: letters, digits, spaces and
    dashes only, at most 16 characters (``DemonstrationRecorder.SanitizeName``)."""
    name = re.sub(r"[^a-zA-Z0-9 -]", "", path.stem)[:NAME_LENGTH]
    return name or "Demo"


def _checkpoint(path: str) -> dict[str, Any]:
    """The checkpoint's behaviors, each ``{"spec", "network"}``; one line when unreadable."""
    import pickle

    from learners.host import checkpoint

    try:
        state = checkpoint.load(path)
        networks = checkpoint.networks(state)
    except FileNotFoundError as error:
        problem = "no such file" if not Path(path).exists() else str(error).splitlines()[0]
        raise TrainingError(f"--checkpoint {path}: {problem}") from None
    except checkpoint.CheckpointError as error:  # it names the file
        raise TrainingError(f"--checkpoint {error}") from None
    except (OSError, ValueError, KeyError, TypeError, RuntimeError, pickle.PickleError) as e:
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise TrainingError(f"--checkpoint {path}: not a readable checkpoint ({first})") from None
    return {name: {"spec": net.spec, "network": net} for name, net in networks.items()}


def _output(out: str) -> Path:
    path = Path(out)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise TrainingError(f"--out {out}: no folder {str(folder)!r} to write it in")
    if path.is_dir():
        raise TrainingError(f"--out {out}: is a folder; name a .demo file")
    try:  # a file can be made there (permissions, a read-only or special file system)
        descriptor, probe = tempfile.mkstemp(prefix=f".{path.name}.", dir=folder)
        os.close(descriptor)
        os.unlink(probe)
    except OSError as error:
        why = error.strerror or type(error).__name__
        problem = f"the folder {str(folder)!r} is not writable ({why})"
        raise TrainingError(f"--out {out}: {problem}") from None
    return path


def _behavior(options: RecordDemoOptions, specs: dict[str, BehaviorSpec]) -> str:
    names = sorted(specs)
    if options.behavior is None:
        if len(names) != 1:
            raise TrainingError(f"--behavior: the build has {len(names)}: {', '.join(names)}")
        return names[0]
    found = [n for n in names if options.behavior in (n, base_name(n))]
    if not found:
        raise TrainingError(
            f"--behavior {options.behavior}: not in {options.env} (it has {', '.join(names)})"
        )
    return found[0]


def _actors(
    options: RecordDemoOptions,
    specs: dict[str, BehaviorSpec],
    recorded: str,
    policies: dict[str, Any],
) -> dict[str, StepActor]:
    """Per behavior of the build: the expert (recorded, --heuristic), the checkpoint's
    policy, else random; a checkpoint policy whose spec differs from the build's is an
    error naming both."""
    actors: dict[str, StepActor] = {}
    for seed, (name, spec) in enumerate(sorted(specs.items()), start=options.seed + 1):
        entry = next((v for k, v in policies.items() if base_name(k) == base_name(name)), None)
        if name == recorded and options.heuristic:
            expert = expert_for(name, options.seed)
            if expert is None:
                known = ", ".join(base_name(b) for b in EXPERTS)
                raise TrainingError(
                    f"--heuristic: no scripted expert for {name} (there are: {known})"
                )
            actors[name] = ExpertActor(expert, spec)
        elif entry is not None:
            if problem := spec_mismatch(spec, entry["spec"]):
                raise TrainingError(
                    f"--checkpoint {options.checkpoint}: its {base_name(name)} policy does not "
                    f"fit {options.env}: {problem}; use a checkpoint trained on this build"
                )
            actors[name] = PolicyActor(entry["network"], options.stochastic)
        elif name == recorded:
            raise TrainingError(
                f"--checkpoint {options.checkpoint}: no policy for {base_name(name)} "
                f"(it has {', '.join(sorted(policies)) or 'none'})"
            )
        else:
            actors[name] = RandomActor(spec, seed)
    return actors


def record_demo(options: RecordDemoOptions) -> Recorded:
    """Launch, act, record, write; the build is closed and its port given back always."""
    assert options.out is not None  # validated
    path = _output(options.out)
    policies = _checkpoint(options.checkpoint) if options.checkpoint else {}
    if policies and options.stochastic:
        import torch

        torch.manual_seed(options.seed)  # sampled actions: the same file for the same seed
    with UnityInstance(record_unity_config(options)) as unity:
        unity.reset()
        specs = dict(unity.behavior_specs)
        behavior = _behavior(options, specs)
        actors = _actors(options, specs, behavior, policies)
        recorder = StepRecorder(specs[behavior], options.actions)
        _run(options, unity, actors, behavior, recorder)
        png = unity.png_sensors(behavior) or frozenset()
    spec = specs[behavior]
    pngs = [i for i, o in enumerate(spec.observation_specs) if o.name in png]
    demo = Demonstration.of_steps(demo_name(path), behavior, spec, recorder.steps)
    _write(path, demo, pngs)
    meta = demo.meta
    return Recorded(path, behavior, meta.steps, meta.episodes, meta.mean_reward)


def _room(options: RecordDemoOptions, recorder: StepRecorder, ends: bool) -> int:
    """How many more records of a kind (episode ends, or decisions) may be taken."""
    if options.episodes is not None:
        return options.episodes - recorder.episodes if ends else sys.maxsize
    assert options.step_limit is not None
    return options.step_limit - len(recorder.steps)


def _run(
    options: RecordDemoOptions,
    unity: UnityInstance,
    actors: dict[str, StepActor],
    behavior: str,
    recorder: StepRecorder,
) -> None:
    """Exchange with the build until the steps (or episodes) asked are recorded: with
    ``--episodes``, up to the episode end that completes them."""
    idle = 0
    while _room(options, recorder, ends=True) > 0 and _room(options, recorder, ends=False) > 0:
        seen = False
        for name, actor in actors.items():
            decisions, terminals = unity.get_steps(name)
            actor.ended([int(a) for a in terminals.agent_id])
            taken = actor.act(decisions) if len(decisions) else None
            if taken is not None:
                unity.set_actions(name, taken)
            if name != behavior:
                continue
            seen = len(decisions) + len(terminals) > 0
            recorder.terminal(terminals, _room(options, recorder, ends=True))
            if taken is not None and _room(options, recorder, ends=True) > 0:
                recorder.decisions(decisions, taken, _room(options, recorder, ends=False))
        idle = 0 if seen else idle + 1
        if idle >= NO_AGENT_STEPS:
            raise TrainingError(
                f"{options.env}: no agent of {behavior} asked for a decision in "
                f"{NO_AGENT_STEPS} steps"
            )
        unity.step()


def _write(path: Path, demo: Demonstration, png: list[int]) -> None:
    """Written beside ``path`` under a temporary name, then renamed over it."""
    descriptor, temporary = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    os.close(descriptor)
    try:
        write_demo(temporary, demo, png)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(temporary, 0o666 & ~umask)  # as an ordinary file, not mkstemp's 0600
        os.replace(temporary, path)
    except DemoError as error:
        raise TrainingError(f"--out {path}: {error.problem}") from None
    except OSError as error:
        raise TrainingError(f"--out {path}: {error.strerror or error}") from None
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(temporary)
