"""Make the unmodified ``mlagents-envs`` 1.1.0 import on modern Python, protobuf and numpy.

mlagents-envs 1.1.0 was generated for protobuf 3.x: its ``*_pb2`` modules build
descriptors by hand, which protobuf 4+ forbids ("Descriptors cannot be created
directly"), and ``mlagents_envs.environment`` imports ``distutils``, which Python 3.12
removed. Rather than patching site-packages, :func:`install` adds two import-time fixes:

* a meta-path finder that serves each ``mlagents_envs.communicator_objects.*_pb2``
  module by reading the serialized ``FileDescriptorProto`` embedded in the original file
  (parsed with :mod:`ast`, never executed) and building the module with protobuf's own
  generated-code builder, exactly as current ``protoc`` output does. The fast backend
  (upb) is kept;
* a minimal ``distutils.version.StrictVersion`` when no ``distutils`` exists.

Importing this module activates both (it calls :func:`install`), so
``import mlagents_compat, mlagents_envs.environment`` just works; nothing is activated by a
``.pth`` file or by merely installing the package. Where the original code already imports
(old protobuf), :func:`install` changes nothing. This module is a leaf: it imports
nothing of ours, so ``unitysim`` may use it too.
"""

from __future__ import annotations

import ast
import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import re
import sys
import threading
import types
from collections.abc import Sequence
from pathlib import Path

__all__ = ["install", "installed_fixes"]

_PB2_PACKAGE = "mlagents_envs.communicator_objects"
_PROBE_MODULE = f"{_PB2_PACKAGE}.header_pb2"

_lock = threading.Lock()
_fixes: tuple[str, ...] | None = None


def install() -> tuple[str, ...]:
    """Activate the fixes this interpreter needs (idempotent); return their names.

    Call it before the first ``import mlagents_envs...`` of generated protobuf code.
    """
    global _fixes
    with _lock:
        if _fixes is None:
            fixes = []
            if importlib.util.find_spec("distutils") is None:
                _install_distutils_shim()
                fixes.append("distutils")
            if not _generated_code_imports():
                sys.meta_path.insert(0, _Pb2Finder())
                fixes.append("protobuf")
            _fixes = tuple(fixes)
        return _fixes


def installed_fixes() -> tuple[str, ...]:
    """The fixes :func:`install` activated, or ``()`` before it ran."""
    return _fixes or ()


# --- protobuf ----------------------------------------------------------------------


def _generated_code_imports() -> bool:
    """Whether the stock generated code imports under this protobuf (old protobuf: yes)."""
    if _PROBE_MODULE in sys.modules:
        return True
    try:
        importlib.import_module(_PROBE_MODULE)
    except ModuleNotFoundError as exc:
        raise ImportError(
            "mlagents-envs is not installed: run the README's set-up command "
            "(it installs mlagents-envs==1.1.0 without its stale pins)"
        ) from exc
    except Exception:  # protobuf 4+: TypeError "Descriptors cannot be created directly"
        sys.modules.pop(_PROBE_MODULE, None)
        return False
    return True


def serialized_file_descriptor(source: str) -> bytes:
    """The serialized ``FileDescriptorProto`` that a generated ``*_pb2`` source embeds.

    Handles protoc 3.x output (``serialized_pb=_b('...')``) and newer output
    (``AddSerializedFile(b'...')``).
    """
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.keyword) and node.arg == "serialized_pb":
            return _literal_bytes(node.value)
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == "AddSerializedFile"
            and node.args
        ):
            return _literal_bytes(node.args[0])
    raise ImportError("no serialized file descriptor found in generated protobuf module")


def _literal_bytes(node: ast.expr) -> bytes:
    if isinstance(node, ast.Call) and len(node.args) == 1:  # _b('...') in protoc 3.x
        node = node.args[0]
    value = ast.literal_eval(node)
    if isinstance(value, str):
        return value.encode("latin1")
    if isinstance(value, bytes):
        return value
    raise ImportError(f"unexpected serialized descriptor literal: {type(value).__name__}")


def _module_for_proto(proto_path: str) -> str:
    """``a/b/c.proto`` -> ``a.b.c_pb2``, the module protoc generates for a dependency."""
    return re.sub(r"\.proto$", "_pb2", proto_path).replace("/", ".")


class _Pb2Loader(importlib.abc.Loader):
    def __init__(self, origin: str) -> None:
        self._origin = origin

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> None:
        return None

    def exec_module(self, module: types.ModuleType) -> None:
        from google.protobuf import descriptor_pb2, descriptor_pool
        from google.protobuf.internal import builder

        serialized = serialized_file_descriptor(Path(self._origin).read_text(encoding="utf-8"))
        file_proto = descriptor_pb2.FileDescriptorProto.FromString(serialized)
        for dependency in file_proto.dependency:
            importlib.import_module(_module_for_proto(dependency))
        descriptor = descriptor_pool.Default().AddSerializedFile(serialized)
        namespace = module.__dict__
        namespace["DESCRIPTOR"] = descriptor
        builder.BuildMessageAndEnumDescriptors(descriptor, namespace)
        builder.BuildTopDescriptorsAndMessages(descriptor, module.__name__, namespace)


class _Pb2Finder(importlib.abc.MetaPathFinder):
    """Serves ``mlagents_envs.communicator_objects.*_pb2`` through :class:`_Pb2Loader`."""

    def find_spec(
        self,
        fullname: str,
        path: Sequence[str] | None,
        target: types.ModuleType | None = None,
    ) -> importlib.machinery.ModuleSpec | None:
        package, _, name = fullname.rpartition(".")
        if package != _PB2_PACKAGE or not name.endswith("_pb2"):
            return None
        original = importlib.machinery.PathFinder.find_spec(fullname, path)
        if original is None or original.origin is None:
            return None
        return importlib.util.spec_from_file_location(
            fullname, original.origin, loader=_Pb2Loader(original.origin)
        )


# --- distutils ---------------------------------------------------------------------

_STRICT_VERSION = re.compile(r"^(\d+)\.(\d+)(?:\.(\d+))?(?:([ab])(\d+))?$", re.ASCII)


class StrictVersion:
    """The part of ``distutils.version.StrictVersion`` mlagents_envs uses."""

    def __init__(self, vstring: str) -> None:
        match = _STRICT_VERSION.match(vstring)
        if match is None:
            raise ValueError(f"invalid version number '{vstring}'")
        major, minor, patch, pre_letter, pre_number = match.groups()
        self.version = (int(major), int(minor), int(patch or 0))
        self.prerelease = (pre_letter, int(pre_number)) if pre_letter else None
        self.vstring = vstring

    def _key(self) -> tuple[tuple[int, int, int], tuple[int, str, int]]:
        pre = (0, *self.prerelease) if self.prerelease else (1, "", 0)
        return self.version, pre

    def __eq__(self, other: object) -> bool:
        return isinstance(other, StrictVersion) and self._key() == other._key()

    def __lt__(self, other: StrictVersion) -> bool:
        return self._key() < other._key()

    def __le__(self, other: StrictVersion) -> bool:
        return self._key() <= other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    def __str__(self) -> str:
        return self.vstring

    def __repr__(self) -> str:
        return f"StrictVersion('{self.vstring}')"


def _install_distutils_shim() -> None:
    package = types.ModuleType("distutils")
    package.__path__ = []  # a package, so "distutils.version" resolves below
    version = types.ModuleType("distutils.version")
    version.StrictVersion = StrictVersion  # type: ignore[attr-defined]
    package.version = version  # type: ignore[attr-defined]
    sys.modules["distutils"] = package
    sys.modules["distutils.version"] = version


install()
