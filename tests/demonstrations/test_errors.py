"""Truncated, corrupt and mismatched files: one :class:`DemoError` line naming the file,
never a protobuf traceback."""

import dataclasses

import numpy as np
import pytest
from mlagents_envs.base_env import ActionSpec

from demonstrations import DemoError, read_demo, write_demo
from tests.demonstrations import samples
from tests.demonstrations.unity_style import UnityStyleWriter, brain, pair, vector_obs


def one_line_error(path, match: str = "") -> DemoError:
    with pytest.raises(DemoError, match=match) as caught:
        read_demo(path)
    error = caught.value
    assert isinstance(error, ValueError)
    assert "\n" not in str(error) and str(error).startswith(f"{path}: ")
    # no chained (protobuf) traceback
    assert error.__cause__ is None and (error.__context__ is None or error.__suppress_context__)
    return error


@pytest.fixture
def small(tmp_path):
    """A small demo of 4 steps and its bytes."""
    path = tmp_path / "small.demo"
    write_demo(path, samples.demonstration(samples.DISCRETE, count=4))
    return path, path.read_bytes()


def test_every_truncation_is_an_error_or_loses_only_the_trailing_copy(tmp_path, small):
    _, data = small
    trailer = len(data) - data[0]  # the undelimited metadata copy starts here
    for cut in range(len(data)):
        cut_path = tmp_path / "cut.demo"
        cut_path.write_bytes(data[:cut])
        if cut >= trailer:
            assert len(read_demo(cut_path).steps) == 4
        else:
            one_line_error(cut_path, "empty file|truncated|corrupt")


def test_a_step_cut_short_says_so(tmp_path, small):
    _, data = small
    (tmp_path / "cut.demo").write_bytes(data[:-40])
    one_line_error(tmp_path / "cut.demo", "truncated: step 3 at byte")


def test_missing_steps_say_how_many(tmp_path):
    writer = UnityStyleWriter("Cut", brain("Cut", branches=(2,)))
    writer.record(pair([vector_obs([1.0])], discrete=[1]))
    data = bytearray(writer.unclosed())  # one record, no trailing copy
    writer.steps = 3  # the metadata claims more records than the file holds
    meta = writer.meta().SerializeToString()
    data[: 1 + len(meta)] = bytes([len(meta)]) + meta
    (tmp_path / "few.demo").write_bytes(bytes(data))
    one_line_error(tmp_path / "few.demo", "metadata says 3 steps, it ends after 1")


def test_a_closed_recording_without_steps(tmp_path):
    writer = UnityStyleWriter("None", brain("None", branches=(2,)))
    (tmp_path / "none.demo").write_bytes(writer.close())
    one_line_error(tmp_path / "none.demo", "no steps, so no behavior spec")


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (lambda d: d[:33] + b"\xff\xff\xff\xff\xff\xff" + d[39:], "not a varint"),
        (
            lambda d: d[:34] + b"\xff" * (d[33]) + d[34 + d[33] :],
            "brain parameters .* does not decode",
        ),
        (lambda d: bytes([40]) + d[1:], "metadata runs past byte 33"),
        (lambda d: b"", "empty file"),
        (lambda d: b"\x00" * 33, "truncated: the file ends at byte 33, before the brain"),
    ],
    ids=["bad-varint", "garbage-brain", "meta-too-long", "empty", "only-meta-area"],
)
def test_corrupt_bytes(tmp_path, small, change, match):
    (tmp_path / "bad.demo").write_bytes(change(small[1]))
    one_line_error(tmp_path / "bad.demo", match)


def test_garbage_in_a_step(tmp_path, small):
    _, data = small
    first = 34 + data[33]  # the first record's length byte
    size = data[first]
    (tmp_path / "bad.demo").write_bytes(
        data[: first + 1] + b"\xff" * size + data[first + 1 + size :]
    )
    one_line_error(tmp_path / "bad.demo", "corrupt: step 0 at byte .* does not decode")


def unity_file(tmp_path, records, api_version=1, name="odd.demo"):
    writer = UnityStyleWriter("Odd", brain("Odd", branches=(2,)), api_version)
    for record in records:
        writer.record(record)
    path = tmp_path / name
    path.write_bytes(writer.close())
    return path


@pytest.mark.parametrize(
    ("records", "match"),
    [
        ([], "no steps, so no behavior spec"),
        (
            [pair([vector_obs([1.0, 2.0])]), pair([vector_obs([1.0])])],
            "step 1: observation 0 has shape",
        ),
        (
            [pair([vector_obs([1.0])]), pair([vector_obs([1.0]), vector_obs([2.0])])],
            "step 1 has 2 observations",
        ),
    ],
    ids=["no-steps", "shape-changes", "sensor-added"],
)
def test_inconsistent_steps(tmp_path, records, match):
    one_line_error(unity_file(tmp_path, records), match)


def test_bad_observations(tmp_path):
    floats = vector_obs([1.0, 2.0, 3.0])
    floats.shape[:] = [4]
    one_line_error(
        unity_file(tmp_path, [pair([floats])]), "observation 0: 3 floats cannot have shape"
    )
    kind = vector_obs([1.0])
    kind.observation_type = 7
    one_line_error(unity_file(tmp_path, [pair([kind])]), "unknown observation type 7")
    png = vector_obs([])
    png.shape[:] = [3, 2, 2]
    png.compression_type, png.compressed_data = 1, b"\x89PNG\r\n\x1a\nnot a png at all"
    one_line_error(unity_file(tmp_path, [pair([png])]), "observation 0: .*PNG")


def test_unsupported_api_version(tmp_path):
    one_line_error(
        unity_file(tmp_path, [pair([vector_obs([1.0])])], api_version=2), "API version 2"
    )


def test_a_spec_that_does_not_match_the_expected_one(tmp_path, small):
    path, _ = small
    assert read_demo(path, expected=samples.DISCRETE).behavior_spec == samples.DISCRETE
    other_actions = samples.DISCRETE._replace(action_spec=ActionSpec(0, (3, 3)))
    with pytest.raises(DemoError, match=r"actions \(continuous 0, discrete branches \[3, 2\]\)"):
        read_demo(path, expected=other_actions)
    sensors = [samples.sensor((9,), "VectorSensor_size9"), samples.sensor((3,), "Ray")]
    with pytest.raises(DemoError, match=r"observation shapes \[\(8,\), \(3,\)\] do not match"):
        read_demo(path, expected=samples.spec(sensors, branches=(3, 2)))
    fewer = samples.spec(sensors[:1], branches=(3, 2))
    with pytest.raises(DemoError) as caught:
        read_demo(path, fewer)
    assert str(caught.value).startswith(f"{path}: ") and "\n" not in str(caught.value)


def test_paths_that_are_no_demo(tmp_path):
    one_line_error(tmp_path / "missing.demo", "no such file or directory")
    (tmp_path / "notes.txt").write_text("hello")
    one_line_error(tmp_path / "notes.txt", r"not a \.demo file")
    (tmp_path / "empty").mkdir()
    one_line_error(tmp_path / "empty", r"no \.demo files in this directory")


def test_what_cannot_be_written_is_refused_naming_the_file(tmp_path):
    demo = samples.demonstration(samples.DISCRETE, count=3)
    path = tmp_path / "out.demo"
    cases = [
        (dataclasses.replace(demo, steps=()), "no steps to write"),
        (
            dataclasses.replace(demo, meta=dataclasses.replace(demo.meta, steps=5)),
            "says 5 steps, it has 3",
        ),
        (
            dataclasses.replace(demo, meta=dataclasses.replace(demo.meta, name="N" * 40)),
            "shorten the name",
        ),
        (
            dataclasses.replace(
                demo, steps=(dataclasses.replace(demo.steps[0], discrete=[1]), *demo.steps[1:])
            ),
            "step 0 has 1 discrete actions",
        ),
        (
            dataclasses.replace(
                demo,
                steps=(
                    *demo.steps[:2],
                    dataclasses.replace(demo.steps[2], observations=(np.zeros(8),)),
                ),
            ),
            "step 2 has observation shapes",
        ),
    ]
    for bad, match in cases:
        with pytest.raises(DemoError, match=match) as caught:
            write_demo(path, bad)
        assert str(caught.value).startswith(f"{path}: ") and "\n" not in str(caught.value)
        assert not path.exists()
