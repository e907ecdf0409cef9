"""record-demo's mistakes: each one line naming what to fix, exit status 2, no file left."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from driver.declaration import declared, flag
from driver.options import RecordDemoOptions
from tests.driver.test_record_demo import build_spec, record, write_checkpoint


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("ckpts")
    basic = folder / "basic.pt"
    write_checkpoint(basic, {"Basic?team=0": build_spec("Basic")})
    wrong = folder / "wrong.pt"  # 3DBall's name, Basic's spec
    write_checkpoint(wrong, {"3DBall?team=0": build_spec("Basic")})
    junk = folder / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    return {"basic": basic, "wrong": wrong, "junk": junk}


CASES = {
    "missing checkpoint": (
        ["--env", "unitysim:Basic", "--checkpoint", "{tmp}/nope.pt"],
        "--checkpoint {tmp}/nope.pt: no such file",
    ),
    "unreadable checkpoint": (
        ["--env", "unitysim:Basic", "--checkpoint", "{junk}"],
        "--checkpoint {junk}: unreadable checkpoint (Weights only load failed.",
    ),
    "behavior not in the build": (
        ["--env", "unitysim:Basic", "--checkpoint", "{basic}", "--behavior", "Walker"],
        "--behavior Walker: not in unitysim:Basic (it has Basic?team=0)",
    ),
    "no policy for the behavior": (
        ["--env", "unitysim:3DBall", "--checkpoint", "{basic}"],
        "--checkpoint {basic}: no policy for 3DBall (it has Basic?team=0)",
    ),
    "spec mismatch": (
        ["--env", "unitysim:3DBall", "--checkpoint", "{wrong}"],
        "--checkpoint {wrong}: its 3DBall policy does not fit unitysim:3DBall: actions "
        "(continuous 2, discrete branches []) do not match the expected (continuous 0, "
        "discrete branches [3]); use a checkpoint trained on this build",
    ),
    "no folder for the output": (
        ["--env", "unitysim:Basic", "--checkpoint", "{basic}", "--out", "{tmp}/no/x.demo"],
        "--out {tmp}/no/x.demo: no folder '{tmp}/no' to write it in",
    ),
    "not a .demo": (
        ["--env", "unitysim:Basic", "--checkpoint", "{basic}", "--out", "{tmp}/x.txt"],
        "--out: a file name ending in .demo, got '{tmp}/x.txt'",
    ),
    "neither policy nor expert": (
        ["--env", "unitysim:Basic"],
        "give --checkpoint PATH (a trained policy) or --heuristic",
    ),
    "no expert for the env": (
        ["--env", "unitysim:3DBall", "--heuristic"],
        "--heuristic: no scripted expert for 3DBall?team=0 "
        "(there are: Hallway, Pyramids, Crawler, PushBlock)",
    ),
    "expert of a real build": (
        ["--env", "/no/such/Game.x86_64", "--heuristic"],
        "--heuristic: scripted experts exist for unitysim builds only, not '/no/such/Game.x86_64'",
    ),
    "steps and episodes": (
        ["--heuristic", "--env", "unitysim:Hallway", "--steps", "3", "--episodes", "2"],
        "give --steps or --episodes, not both",
    ),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_one_line_error(case, tmp_path, checkpoints):
    args, message = CASES[case]
    names = {"tmp": tmp_path, **checkpoints}
    argv = [a.format(**names) for a in args]
    if "--out" not in argv:
        argv += ["--out", str(tmp_path / "demo.demo")]
    code, _, stderr = record(tmp_path, *argv, timeout=60)
    lines = stderr.strip().splitlines()
    assert (code, len(lines)) == (2, 1), stderr
    expected = f"error: {message.format(**names)}"
    assert lines[0] == expected or (expected.endswith(".") and lines[0].startswith(expected))
    assert [p.name for p in tmp_path.iterdir() if p.name != "ports"] == []


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_unwritable_folder(tmp_path, checkpoints):
    folder = tmp_path / "locked"
    folder.mkdir(mode=0o500)
    out = folder / "x.demo"
    argv = ["--env", "unitysim:Basic", "--checkpoint", str(checkpoints["basic"])]
    code, _, stderr = record(tmp_path, *argv, "--out", str(out), timeout=60)
    assert (code, stderr.strip()) == (
        2,
        f"error: --out {out}: the folder '{folder}' is not writable",
    )
    assert list(folder.iterdir()) == []


def test_a_folder_no_file_can_be_made_in(tmp_path, checkpoints):
    argv = ["--env", "unitysim:Basic", "--checkpoint", str(checkpoints["basic"])]
    code, _, stderr = record(tmp_path, *argv, "--out", "/proc/x.demo", timeout=60)
    assert code == 2
    assert stderr.strip().splitlines() == [
        "error: --out /proc/x.demo: the folder '/proc' is not writable (No such file or directory)"
    ]


def test_the_docs_list_every_option():
    text = (Path(__file__).resolve().parents[2] / "docs/demonstrations.md").read_text()
    names = [flag(item.name) for item, _ in declared(RecordDemoOptions)]
    assert [name for name in names if f"`{name}`" not in text] == []
