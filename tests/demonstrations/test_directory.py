"""A directory: every ``.demo`` file in it (as ML-Agents' ``get_demo_files``), by name."""

import pytest

from demonstrations import DemoError, demo_files, read_demo, read_demos, write_demo
from tests.demonstrations import samples


@pytest.fixture
def folder(tmp_path):
    first = samples.demonstration(samples.DISCRETE, count=5, seed=1)
    second = samples.demonstration(samples.DISCRETE, count=7, seed=2)
    write_demo(tmp_path / "b.demo", second)
    write_demo(tmp_path / "a.demo", first)
    (tmp_path / "notes.txt").write_text("not a demo")
    (tmp_path / "sub.demo").mkdir()  # a directory with the suffix is no file
    return tmp_path, first, second


def test_every_demo_file_by_name(folder):
    path, first, second = folder
    assert demo_files(path) == [path / "a.demo", path / "b.demo"]
    assert read_demos(path) == (first, second)
    assert demo_files(path / "a.demo") == [path / "a.demo"]


def test_a_directory_reads_as_one_demonstration(folder):
    path, first, second = folder
    demo = read_demo(path, expected=samples.DISCRETE)
    assert demo.steps == first.steps + second.steps
    assert demo.behavior_spec == samples.DISCRETE
    assert (demo.meta.name, demo.meta.steps) == (path.name, 12)
    assert demo.meta.episodes == first.meta.episodes + second.meta.episodes
    reward = first.meta.mean_reward * first.meta.episodes + second.meta.mean_reward * 2
    assert demo.meta.mean_reward == pytest.approx(reward / demo.meta.episodes)


def test_files_of_another_behavior_are_named(folder):
    path, _, _ = folder
    write_demo(path / "c.demo", samples.demonstration(samples.CONTINUOUS, count=2))
    with pytest.raises(DemoError, match=r"c\.demo: actions .* \(compared with a\.demo\)$"):
        read_demo(path)


def test_a_bad_file_in_a_directory_is_named(folder):
    path, _, _ = folder
    (path / "broken.demo").write_bytes(b"\x05\x08")
    with pytest.raises(DemoError, match=r"broken\.demo: truncated"):
        read_demo(path)
