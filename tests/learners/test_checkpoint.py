"""Checkpoint files survive a kill mid-save: each is written to a temporary name, synced,
then renamed, so a checkpoint's name never holds a partial file."""

from __future__ import annotations

import subprocess
import sys

import pytest

from learners.host import checkpoint

KILLER = """
import os, random, signal, sys, time, torch
from learners.host import checkpoint
folder, rng = sys.argv[1], random.Random(7)
state = {"step": 0, "version": 0, "behaviors": {"B": {"steps": 0, "w": torch.randn(4_000_000)}}}
for kill in range(10):  # a child saves without pause; killed at a random moment after its first
    child = os.fork()
    if child == 0:
        for step in range(kill * 1000, (kill + 1) * 1000):
            state["step"] = state["behaviors"]["B"]["steps"] = step
            checkpoint.save(f"{folder}/step-{step:010d}.pt", state)
        os._exit(0)
    first, deadline = f"{folder}/step-{kill * 1000:010d}.pt", time.monotonic() + 60
    while not os.path.exists(first) and time.monotonic() < deadline:  # a loaded machine
        time.sleep(0.01)  # poll interval: the first checkpoint's file
    time.sleep(rng.uniform(0.05, 0.4))  # the kill's random moment, not a wait
    os.kill(child, signal.SIGKILL)
    os.waitpid(child, 0)
"""


@pytest.mark.integration
def test_a_process_killed_while_it_saves_leaves_only_whole_checkpoints(tmp_path):
    """Checkpoints of 16 MB saved back to back, the saver SIGKILLed ten times: the kills
    land mid-save (their temporary files stay), yet every ``.pt`` is whole and the newest
    loads."""
    subprocess.run([sys.executable, "-c", KILLER, str(tmp_path)], check=True, timeout=120)
    assert list(tmp_path.glob(".*.tmp")), "no kill landed during a save"
    files = checkpoint.newest_first(tmp_path)
    assert len(files) >= 10
    for path in files:
        checkpoint.read(path)  # raises on a partial file
    assert checkpoint.load(tmp_path)["step"] == int(files[0].stem.split("-")[1])


def test_an_unreadable_file_is_named(tmp_path):
    path = tmp_path / "step-0000000001.pt"
    path.write_bytes(b"PK\x03\x04 cut short")
    with pytest.raises(checkpoint.CheckpointError, match=f"{path}: unreadable checkpoint"):
        checkpoint.read(path)


def test_a_checkpoint_of_another_format_is_refused_in_one_line_naming_what_to_do(tmp_path):
    """The layout's version refuses what it cannot read, before any state is loaded: a file
    of format 1 lacks SAC's gradient counts, self-play's keys and the memory settings."""
    import torch

    path = tmp_path / "step-0000000001.pt"
    torch.save({"format": checkpoint.FORMAT - 1, "step": 1, "version": 1, "behaviors": {}}, path)
    with pytest.raises(checkpoint.CheckpointError) as caught:
        checkpoint.read(path)
    message = str(caught.value)
    assert "\n" not in message and message.startswith(f"{path}: a checkpoint of format 1")
    assert "--run-id" in message
    checkpoint.save(path, {"step": 2, "version": 2, "behaviors": {}})
    assert checkpoint.read(path)["format"] == checkpoint.FORMAT
