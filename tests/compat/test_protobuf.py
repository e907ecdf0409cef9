"""Every generated message of mlagents-envs works under the installed protobuf."""

import importlib
import pkgutil

import mlagents_envs.communicator_objects as communicator_objects
import pytest
from google.protobuf.descriptor import Descriptor, FieldDescriptor
from google.protobuf.internal import api_implementation
from google.protobuf.message import Message

import mlagents_compat as compat


def _pb2_modules():
    for info in pkgutil.iter_modules(communicator_objects.__path__):
        if info.name.endswith("_pb2"):
            yield importlib.import_module(f"{communicator_objects.__name__}.{info.name}")


def _message_classes():
    """Every message class, nested ones (e.g. ObservationProto.FloatData) included."""

    def walk(cls):
        yield cls
        for nested in cls.DESCRIPTOR.nested_types:
            if not nested.GetOptions().map_entry:
                yield from walk(getattr(cls, nested.name))

    for module in _pb2_modules():
        for name in module.DESCRIPTOR.message_types_by_name:
            yield from walk(getattr(module, name))


def _sample(field: FieldDescriptor):
    if field.type == FieldDescriptor.TYPE_ENUM:
        return field.enum_type.values[-1].number
    if field.type == FieldDescriptor.TYPE_BYTES:
        return b"\x89PNG\x00\xff"
    return {
        FieldDescriptor.CPPTYPE_BOOL: True,
        FieldDescriptor.CPPTYPE_STRING: "abc?team=1",
        FieldDescriptor.CPPTYPE_FLOAT: 1.5,
        FieldDescriptor.CPPTYPE_DOUBLE: 2.5,
    }.get(field.cpp_type, 7)


def _is_repeated(field: FieldDescriptor) -> bool:
    # protobuf 3.20 has only ``label``; protobuf 7 deprecates it for ``is_repeated``.
    if hasattr(field, "is_repeated"):
        return field.is_repeated
    return field.label == FieldDescriptor.LABEL_REPEATED


def _fill(message: Message, depth: int = 0) -> None:
    """Set every field (the first of each oneof) to a non-default value, recursively."""
    descriptor: Descriptor = message.DESCRIPTOR
    for field in descriptor.fields:
        oneof = field.containing_oneof
        if oneof is not None and oneof.fields[0] is not field:
            continue
        value = getattr(message, field.name)
        if field.message_type is not None and field.message_type.GetOptions().map_entry:
            value_field = field.message_type.fields_by_name["value"]
            key = _sample(field.message_type.fields_by_name["key"])
            if value_field.message_type is not None:
                _fill(value[key], depth + 1)
            else:
                value[key] = _sample(value_field)
        elif _is_repeated(field):
            if field.message_type is not None:
                if depth < 4:
                    _fill(value.add(), depth + 1)
                    _fill(value.add(), depth + 1)
            else:
                value.extend([_sample(field), _sample(field)])
        elif field.message_type is not None:
            if depth < 4:
                _fill(value, depth + 1)
        else:
            setattr(message, field.name, _sample(field))


MESSAGE_CLASSES = sorted(_message_classes(), key=lambda cls: cls.DESCRIPTOR.full_name)


def test_all_generated_modules_found():
    assert len(MESSAGE_CLASSES) == 23
    names = {cls.DESCRIPTOR.name for cls in MESSAGE_CLASSES}
    assert {"UnityMessageProto", "AgentInfoProto", "FloatData", "ListAgentInfoProto"} <= names


@pytest.mark.parametrize("cls", MESSAGE_CLASSES, ids=lambda cls: cls.DESCRIPTOR.name)
def test_message_round_trips(cls):
    message = cls()
    _fill(message)
    data = message.SerializeToString()
    assert data or not cls.DESCRIPTOR.fields, "a filled message must serialize to something"
    parsed = cls.FromString(data)
    assert parsed == message
    assert parsed.SerializeToString(deterministic=True) == message.SerializeToString(
        deterministic=True
    )


def test_fast_backend_in_use():
    assert api_implementation.Type() != "python"


def test_fix_reported_only_when_needed():
    major = int(__import__("google.protobuf").protobuf.__version__.split(".")[0])
    assert ("protobuf" in compat.installed_fixes()) == (major >= 4)


def test_module_level_enums_and_wire_bytes():
    from mlagents_envs.communicator_objects import command_pb2, observation_pb2
    from mlagents_envs.communicator_objects.header_pb2 import HeaderProto
    from mlagents_envs.communicator_objects.unity_message_pb2 import UnityMessageProto

    assert (command_pb2.STEP, command_pb2.RESET, command_pb2.QUIT) == (0, 1, 2)
    assert (observation_pb2.NONE, observation_pb2.PNG) == (0, 1)
    assert observation_pb2.GOAL_SIGNAL == 1
    # Encodings checked against the protocol note (empty 200 and close 400 messages).
    ok = UnityMessageProto(header=HeaderProto(status=200)).SerializeToString()
    close = UnityMessageProto(header=HeaderProto(status=400)).SerializeToString()
    assert ok == bytes.fromhex("0a0308c801")
    assert close == bytes.fromhex("0a03089003")


def test_grpc_stub_module_imports():
    from mlagents_envs.communicator_objects import unity_to_external_pb2_grpc as grpc_mod
    from mlagents_envs.communicator_objects.unity_message_pb2 import UnityMessageProto

    assert grpc_mod.UnityToExternalProtoServicer.Exchange
    assert UnityMessageProto.__module__.endswith("unity_message_pb2")


def test_serialized_descriptor_extraction_handles_both_protoc_styles():
    old = "DESCRIPTOR = _descriptor.FileDescriptor(name='x', serialized_pb=_b('\\n\\x01\\xff'))"
    new = "DESCRIPTOR = _pool.Default().AddSerializedFile(b'\\n\\x01\\xff')"
    assert compat.serialized_file_descriptor(old) == b"\n\x01\xff"
    assert compat.serialized_file_descriptor(new) == b"\n\x01\xff"
    with pytest.raises(ImportError):
        compat.serialized_file_descriptor("x = 1")


def test_install_is_idempotent():
    assert compat.install() == compat.install() == compat.installed_fixes()


def test_strict_version_shim_matches_distutils_semantics():
    version = compat.StrictVersion("1.5.0")
    assert version.version == (1, 5, 0)
    assert compat.StrictVersion("1.5") == compat.StrictVersion("1.5.0")
    assert compat.StrictVersion("1.5.0a1") < compat.StrictVersion("1.5.0")
    assert compat.StrictVersion("0.9.9") < compat.StrictVersion("1.0.0")
    with pytest.raises(ValueError, match="invalid version number"):
        compat.StrictVersion("one.two")


def test_environment_version_check_uses_working_strict_version():
    from mlagents_envs.environment import UnityEnvironment

    check = UnityEnvironment._check_communication_compatibility
    assert check("1.5.0", "1.5.0", "3.0.0")
    assert check("1.9.2", "1.5.0", "3.0.0")
    assert not check("2.0.0", "1.5.0", "3.0.0")
    assert not check("0.9.0", "1.5.0", "3.0.0")
