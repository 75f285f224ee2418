"""Message and service types: rosbags' offline type stores, CDR <-> plain dicts, type hashes.

A `TypeRegistry` holds the message definitions of one ROS 2 distribution (rosbags ships
them: ``humble``, ``iron``, ``jazzy`` (default), ``kilted``), the services rra-agent talks
to (parameters, lifecycle, std_srvs) and whatever custom ``.msg``/``.srv``/``.idl`` files a
package brings. Messages go in and out as plain dicts (numeric arrays as lists; a missing
field takes its zero value); a wrong field, a value that does not fit or bytes that are not
CDR of the type are a `FieldError` / `DecodeError`, never another exception.

Type hashes are RIHS01 (REP-2016) as rosidl computes them, which rmw_zenoh puts in its key
expressions; Humble has none (``TypeHashNotSupported``).
"""

from __future__ import annotations

import difflib
import types as pytypes
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore
from rosbags.typesys.base import Nodetype
from rosbags.typesys.store import Typestore

from rra_agent.ros2.errors import DecodeError, FieldError, UnknownType
from rra_agent.ros2.names import NO_TYPE_HASH, check_type_name

DISTROS = {
    "humble": Stores.ROS2_HUMBLE,
    "iron": Stores.ROS2_IRON,
    "jazzy": Stores.ROS2_JAZZY,
    "kilted": Stores.ROS2_KILTED,
}
DEFAULT_DISTRO = "jazzy"
#: Distributions without type hashes in their key expressions.
NO_HASH_DISTROS = {"humble"}

EVENT_INFO = "service_msgs/msg/ServiceEventInfo"
#: Services rra-agent calls or serves, as .srv text (request ``---`` response); rosbags'
#: stores hold messages only.
SERVICES = {
    "rcl_interfaces/srv/GetParameters": "string[] names\n---\nParameterValue[] values\n",
    "rcl_interfaces/srv/SetParameters": (
        "Parameter[] parameters\n---\nSetParametersResult[] results\n"
    ),
    "rcl_interfaces/srv/SetParametersAtomically": (
        "Parameter[] parameters\n---\nSetParametersResult result\n"
    ),
    "rcl_interfaces/srv/ListParameters": (
        "uint64 DEPTH_RECURSIVE=0\nstring[] prefixes\nuint64 depth\n---\n"
        "ListParametersResult result\n"
    ),
    "lifecycle_msgs/srv/ChangeState": "Transition transition\n---\nbool success\n",
    "lifecycle_msgs/srv/GetState": "---\nState current_state\n",
    "lifecycle_msgs/srv/GetAvailableStates": "---\nState[] available_states\n",
    "lifecycle_msgs/srv/GetAvailableTransitions": (
        "---\nTransitionDescription[] available_transitions\n"
    ),
    "std_srvs/srv/Empty": "---\n",
    "std_srvs/srv/Trigger": "---\nbool success\nstring message\n",
    "std_srvs/srv/SetBool": "bool data\n---\nbool success\nstring message\n",
}

_NUMERIC = {
    "bool": np.bool_,
    "byte": np.uint8,
    "char": np.uint8,
    "int8": np.int8,
    "uint8": np.uint8,
    "int16": np.int16,
    "uint16": np.uint16,
    "int32": np.int32,
    "uint32": np.uint32,
    "int64": np.int64,
    "uint64": np.uint64,
    "float32": np.float32,
    "float64": np.float64,
}
_INTS = {k for k in _NUMERIC if k.startswith(("int", "uint")) or k in ("byte", "char")}
_MISSING = object()


class TypeRegistry:
    """The message and service types of one ROS 2 distribution, and a package's own."""

    def __init__(self, distro: str = DEFAULT_DISTRO) -> None:
        if distro not in DISTROS:
            raise UnknownType(
                f"unknown ROS 2 distribution {distro!r}: one of {', '.join(sorted(DISTROS))}"
            )
        self.distro = distro
        self.store: Typestore = get_typestore(DISTROS[distro])
        self.services: set[str] = set()
        if EVENT_INFO not in self.store.fielddefs:  # Humble has no service events
            self.register_msg(EVENT_INFO, "uint8 event_type\nbuiltin_interfaces/Time stamp\n"
                              "char[16] client_gid\nint64 sequence_number\n")
        for srv, text in SERVICES.items():
            self.register_srv(srv, text)

    # -- registering ----------------------------------------------------------------------

    def register_msg(self, ros_type: str, text: str) -> None:
        """Register ``pkg/msg/Type`` from its .msg text (unqualified names: ``pkg``'s)."""
        check_type_name(ros_type, "msg")
        self._register(lambda: get_types_from_msg(text, ros_type), ros_type)

    def register_idl(self, text: str, origin: str = "IDL") -> list[str]:
        """Register every type of an .idl text; returns their names."""
        found: dict[str, Any] = {}

        def parse() -> dict[str, Any]:
            found.update(get_types_from_idl(text))
            return found

        self._register(parse, origin)
        return sorted(found)

    def register_srv(self, srv_type: str, text: str) -> None:
        """Register ``pkg/srv/Name`` from its .srv text: its request, response and event
        messages and the service type itself (what its type hash is computed over)."""
        pkg, _, name = check_type_name(srv_type, "srv")
        request, sep, response = text.partition("\n---")
        if not sep and not text.startswith("---"):
            raise FieldError(f"{srv_type}: a .srv text needs a '---' line")
        if text.startswith("---"):
            request, response = "", text[3:]
        typs: dict[str, Any] = {}
        for part, body in (("Request", request), ("Response", response.lstrip("-\n"))):
            parsed = get_types_from_msg(body, f"{pkg}/msg/{name}_{part}")
            typs[f"{pkg}/srv/{name}_{part}"] = parsed.pop(f"{pkg}/msg/{name}_{part}")
            typs.update(parsed)
        base = f"{pkg}/srv/{name}"
        typs[f"{base}_Event"] = ([], [
            ("info", (Nodetype.NAME, "service_msgs/msg/ServiceEventInfo")),
            ("request", (Nodetype.SEQUENCE, ((Nodetype.NAME, f"{base}_Request"), 1))),
            ("response", (Nodetype.SEQUENCE, ((Nodetype.NAME, f"{base}_Response"), 1))),
        ])
        typs[base] = ([], [
            ("request_message", (Nodetype.NAME, f"{base}_Request")),
            ("response_message", (Nodetype.NAME, f"{base}_Response")),
            ("event_message", (Nodetype.NAME, f"{base}_Event")),
        ])
        self._register(lambda: typs, srv_type)
        self.services.add(srv_type)

    def register_folder(self, folder: str | Path) -> list[str]:
        """Register a package's interface files: ``<pkg>/msg/<Type>.msg``,
        ``<pkg>/srv/<Name>.srv`` and any ``*.idl`` under ``folder``; returns the types."""
        root = Path(folder)
        if not root.is_dir():
            raise UnknownType(f"{root}: no such folder of message definitions")
        msgs: dict[str, Any] = {}
        for path in sorted(root.rglob("*.msg")):
            name = f"{path.parent.parent.name}/msg/{path.stem}"
            check_type_name(name, "msg")
            text = path.read_text()
            msgs.update(self._parse(lambda t=text, n=name: get_types_from_msg(t, n), path))
        self._register(lambda: msgs, str(root))
        names = sorted(msgs)
        for path in sorted(root.rglob("*.srv")):
            name = f"{path.parent.parent.name}/srv/{path.stem}"
            self._wrap(lambda p=path, n=name: self.register_srv(n, p.read_text()), path)
            names.append(name)
        for path in sorted(root.rglob("*.idl")):
            names += self.register_idl(path.read_text(), str(path))
        return names

    def _parse(self, parse: Any, origin: Path) -> dict[str, Any]:
        return self._wrap(parse, origin)  # type: ignore[no-any-return]

    @staticmethod
    def _wrap(call: Any, origin: object) -> Any:
        try:
            return call()
        except (FieldError, UnknownType):
            raise
        except Exception as e:
            raise UnknownType(f"{origin}: not a valid definition: {_one_line(e)}") from None

    def _register(self, parse: Any, origin: str) -> None:
        typs = self._wrap(parse, origin)
        missing = sorted(
            sub
            for _, fields in typs.values()
            for _, desc in fields
            for sub in _names_in(desc)
            if sub not in typs and sub not in self.store.fielddefs
        )
        if missing:
            raise UnknownType(f"{origin}: refers to unknown type(s) {', '.join(missing)}")
        self._wrap(lambda: self.store.register(typs), origin)

    # -- looking up -----------------------------------------------------------------------

    def has(self, ros_type: str) -> bool:
        return ros_type in self.store.fielddefs

    def require(self, ros_type: str) -> str:
        if ros_type not in self.store.fielddefs:
            check_type_name(ros_type)
            raise UnknownType(
                f"unknown ROS 2 type {ros_type!r} in {self.distro} (a type of your own: put "
                "<pkg>/msg/<Type>.msg in the folder of rra.yaml's ros2: {interfaces})"
            )
        return ros_type

    def require_service(self, srv_type: str) -> str:
        check_type_name(srv_type, "srv")
        if srv_type not in self.services:
            raise UnknownType(f"unknown ROS 2 service type {srv_type!r}")
        return srv_type

    def field_names(self, ros_type: str) -> list[str]:
        return [name for name, _ in self.store.fielddefs[self.require(ros_type)][1]]

    def type_hash(self, ros_type: str) -> str:
        """The RIHS01 hash of a message or service type as rosidl computes it (rosbags' own
        differs for ``char`` fields, which rosidl maps to uint8), or `NO_TYPE_HASH` for a
        distribution without type hashes."""
        self.require(ros_type)
        if self.distro in NO_HASH_DISTROS:
            return NO_TYPE_HASH
        proxy = pytypes.SimpleNamespace(fielddefs=_CharAsUint8(self.store.fielddefs))
        return Typestore.hash_rihs01(proxy, ros_type)  # type: ignore[arg-type]

    def msg_text(self, ros_type: str) -> str:
        """The .msg text of a type alone (no dependencies), as ROS would write it."""
        text, _ = self.store.generate_msgdef(self.require(ros_type), ros_version=2)
        own = text.split("=" * 80 + "\n", 1)[0]
        return own if own.endswith("\n") or not own else own + "\n"

    def dependencies(self, ros_type: str) -> list[str]:
        """Every type ``ros_type`` refers to, itself excluded, depth first."""
        seen: dict[str, None] = {}

        def walk(typ: str) -> None:
            for _, desc in self.store.fielddefs[self.require(typ)][1]:
                for sub in _names_in(desc):
                    if sub not in seen:
                        seen[sub] = None
                        walk(sub)

        walk(ros_type)
        return list(seen)

    def export(self, folder: str | Path, names: list[str]) -> list[Path]:
        """Write ``<pkg>/msg/<Type>.msg`` (and ``<pkg>/srv/<Name>.srv``) for ``names`` and
        every type they use under ``folder``: the offline message directory other ROS 2
        tools without ROS (e.g. zenoh-ros2-sdk's registry) read."""
        root = Path(folder)
        todo: dict[str, None] = {}
        for name in names:
            if name in self.services:
                todo[name] = None
                for part in ("Request", "Response"):
                    todo.update(dict.fromkeys(self.dependencies(f"{name}_{part}")))
            else:
                todo[self.require(name)] = None
                todo.update(dict.fromkeys(self.dependencies(name)))
        written = []
        for name in todo:
            pkg, kind, base = check_type_name(name)
            if kind == "srv" and name not in self.services:
                continue
            if kind == "srv":
                parts = [self.msg_text(f"{name}_{p}") for p in ("Request", "Response")]
                text = f"{parts[0]}---\n{parts[1]}"
                for part, body in zip(("Request", "Response"), parts, strict=True):
                    # what tools look up for a service's messages before the .srv
                    sub = root / pkg / kind / f"{base}_{part}.msg"
                    sub.parent.mkdir(parents=True, exist_ok=True)
                    sub.write_text(body)
                    written.append(sub)
            else:
                text = self.msg_text(name)
            path = root / pkg / kind / f"{base}.{kind}"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
            written.append(path)
        return written

    # -- CDR ------------------------------------------------------------------------------

    def encode(self, ros_type: str, value: Mapping[str, Any] | object) -> bytes:
        """CDR (little endian, with its 4-byte header) of a message given as a dict."""
        obj = self.build(ros_type, value)
        try:
            return bytes(self.store.serialize_cdr(obj, ros_type))
        except Exception as e:
            raise FieldError(f"{ros_type}: value does not fit the type: {_one_line(e)}") from None

    def decode(self, ros_type: str, data: bytes | memoryview) -> dict[str, Any]:
        """The message in CDR ``data`` as a plain dict; `DecodeError` if it is not one."""
        self.require(ros_type)
        raw = bytes(data)
        if len(raw) < 4 or raw[0] != 0 or raw[1] not in (0, 1):
            raise DecodeError(f"{len(raw)} bytes are not CDR (no CDR encapsulation header)")
        try:
            obj = self.store.deserialize_cdr(raw, ros_type)
        except Exception as e:
            raise DecodeError(
                f"{len(raw)} bytes are not a CDR {ros_type}: {_one_line(e)}"
            ) from None
        return self.plain(ros_type, obj)  # type: ignore[no-any-return]

    def build(self, ros_type: str, value: Mapping[str, Any] | object, path: str = "") -> object:
        """A rosbags message object from a dict (missing fields: zero values)."""
        self.require(ros_type)
        cls = self.store.types[ros_type]
        if isinstance(value, cls):
            return value
        if not isinstance(value, Mapping):
            raise FieldError(f"{path or ros_type}: expected a mapping for {ros_type}, "
                             f"got {type(value).__name__}")
        fields = self.store.fielddefs[ros_type][1]
        names = {n for n, _ in fields}
        unknown = sorted(set(value) - names)
        if unknown:
            raise FieldError(
                f"{_join(path, unknown[0])}: no such field in {ros_type} (fields: "
                f"{', '.join(n for n, _ in fields) or 'none'})"
            )
        kwargs = {
            n: self._value(desc, value.get(n, _MISSING), _join(path, n)) for n, desc in fields
        }
        return cls(**kwargs)

    def _value(self, desc: Any, v: Any, path: str) -> Any:
        node, rest = desc
        if node == Nodetype.NAME:
            return self.build(rest, {} if v is _MISSING else v, path)
        if node == Nodetype.BASE:
            return _base(rest[0], rest[1], v, path)
        (sub_node, sub_rest), size = rest
        fixed = node == Nodetype.ARRAY
        items = ([] if not fixed else [_MISSING] * size) if v is _MISSING else v
        if isinstance(items, np.ndarray):
            items = items.tolist()
        if isinstance(items, (str, bytes)) and not (sub_node == Nodetype.BASE and isinstance(
                items, bytes)):
            raise FieldError(f"{path}: expected a list, got {type(items).__name__}")
        items = list(items) if isinstance(items, (list, tuple, bytes)) else _not_list(items, path)
        if fixed and len(items) != size:
            raise FieldError(f"{path}: expected {size} elements, got {len(items)}")
        if not fixed and size and len(items) > size:
            raise FieldError(f"{path}: at most {size} elements, got {len(items)}")
        if sub_node == Nodetype.BASE and sub_rest[0] in _NUMERIC:
            vals = [_base(sub_rest[0], 0, x, f"{path}.{i}") for i, x in enumerate(items)]
            return np.array(vals, dtype=_NUMERIC[sub_rest[0]])
        return [self._value((sub_node, sub_rest), x, f"{path}.{i}") for i, x in enumerate(items)]

    def plain(self, ros_type: str, obj: Any) -> Any:
        """A rosbags message as plain Python: dicts of its fields (no constants), lists,
        numbers, strings."""
        return {
            n: self._plain_value(desc, getattr(obj, n))
            for n, desc in self.store.fielddefs[ros_type][1]
        }

    def _plain_value(self, desc: Any, v: Any) -> Any:
        node, rest = desc
        if node == Nodetype.NAME:
            return self.plain(rest, v)
        if node == Nodetype.BASE:
            v = v.item() if isinstance(v, np.generic) else v
            # rosbags reads ``byte`` as int8; ROS 2's byte (octet) is 0..255
            return v % 256 if rest[0] == "byte" and isinstance(v, int) else v
        if isinstance(v, np.ndarray):
            return (v.view(np.uint8) if v.dtype == np.int8 and rest[0][1][0] == "byte"
                    else v).tolist()
        return [self._plain_value(rest[0], x) for x in v]

    # -- fields ---------------------------------------------------------------------------

    def field_type(self, ros_type: str, path: str) -> str:
        """The ROS type of the field at a dotted ``path`` (``header.stamp.sec``,
        ``cell_voltage.0``): e.g. ``float32``, ``string``, ``float32[]`` or a message type;
        `FieldError` naming the fields there if it does not exist."""
        self.require(ros_type)
        desc: Any = (Nodetype.NAME, ros_type)
        done = ""
        for part in path.split("."):
            node, rest = desc
            if node == Nodetype.NAME:
                fields = dict(self.store.fielddefs[rest][1])
                if part not in fields:
                    raise FieldError(_no_field(ros_type, _join(done, part), rest, list(fields)))
                desc = fields[part]
            elif node in (Nodetype.ARRAY, Nodetype.SEQUENCE) and part.isdigit():
                if node == Nodetype.ARRAY and int(part) >= rest[1]:
                    raise FieldError(f"{ros_type}: {_join(done, part)} is out of range "
                                     f"(an array of {rest[1]})")
                desc = rest[0]
            else:
                raise FieldError(f"{ros_type}: {done or ros_type} is {_describe(desc)}, "
                                 f"it has no field {part!r}")
            done = _join(done, part)
        return _describe(desc)




def _no_field(ros_type: str, path: str, owner: str, fields: list[str]) -> str:
    """"X has no field 'p'": the closest field first (did you mean), then all of them."""
    close = difflib.get_close_matches(path.rsplit(".", 1)[-1], fields, n=1)
    hint = f"did you mean {close[0]!r}? " if close else ""
    return f"{ros_type} has no field {path!r} ({hint}{owner} has: {', '.join(fields) or 'none'})"


def get_field(message: Mapping[str, Any], path: str) -> Any:
    """The value at a dotted ``path`` of a decoded message (indexes as numbers: ``a.0.b``)."""
    value: Any = message
    for part in path.split("."):
        if isinstance(value, Mapping) and part in value:
            value = value[part]
        elif isinstance(value, list) and part.isdigit() and int(part) < len(value):
            value = value[int(part)]
        else:
            raise FieldError(f"the message has no field {path!r} (at {part!r})")
    return value


def _base(typ: str, bound: int, v: Any, path: str) -> Any:
    if typ == "string":
        if v is _MISSING:
            return ""
        if not isinstance(v, str):
            raise FieldError(f"{path}: expected a string, got {type(v).__name__}")
        if bound and len(v) > bound:
            raise FieldError(f"{path}: at most {bound} characters, got {len(v)}")
        return v
    if v is _MISSING:
        return False if typ == "bool" else 0 if typ in _INTS else 0.0
    if typ == "bool":
        if not isinstance(v, (bool, np.bool_)):
            raise FieldError(f"{path}: expected a bool, got {type(v).__name__}")
        return bool(v)
    if typ in _INTS:
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
            raise FieldError(f"{path}: expected an integer ({typ}), got {type(v).__name__}")
        info = np.iinfo(_NUMERIC[typ])
        if not info.min <= int(v) <= info.max:
            raise FieldError(f"{path}: {v} is out of range for {typ}")
        return int(v)
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise FieldError(f"{path}: expected a number ({typ}), got {type(v).__name__}")
    return float(v)


def _not_list(v: Any, path: str) -> list[Any]:
    raise FieldError(f"{path}: expected a list, got {type(v).__name__}")


def _names_in(desc: Any) -> Iterator[str]:
    node, rest = desc
    if node == Nodetype.NAME:
        yield rest
    elif node in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        yield from _names_in(rest[0])


def _describe(desc: Any) -> str:
    node, rest = desc
    if node == Nodetype.NAME:
        return str(rest)
    if node == Nodetype.BASE:
        return f"string<={rest[1]}" if rest[0] == "string" and rest[1] else str(rest[0])
    inner = _describe(rest[0])
    if node == Nodetype.ARRAY:
        return f"{inner}[{rest[1]}]"
    return f"{inner}[<={rest[1]}]" if rest[1] else f"{inner}[]"


def _join(path: str, part: str) -> str:
    return f"{path}.{part}" if path else part


def _one_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0]}" if text else type(e).__name__


class _CharAsUint8(Mapping[str, Any]):
    """Field definitions with ``char`` read as ``uint8``, as rosidl's type descriptions
    have it (a .msg ``char`` becomes an IDL ``uint8``)."""

    def __init__(self, fielddefs: Mapping[str, Any]) -> None:
        self._defs = fielddefs

    def __getitem__(self, typ: str) -> Any:
        consts, fields = self._defs[typ]
        return consts, [(n, _char_fix(d)) for n, d in fields]

    def __iter__(self) -> Iterator[str]:
        return iter(self._defs)

    def __len__(self) -> int:
        return len(self._defs)


def _char_fix(desc: Any) -> Any:
    node, rest = desc
    if node == Nodetype.BASE and rest[0] == "char":
        return (node, ("uint8", rest[1]))
    if node in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        return (node, (_char_fix(rest[0]), rest[1]))
    return desc
