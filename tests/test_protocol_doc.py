"""docs/protocol.md stays true to the code.

Checked against `rra_agent.bus.messages`, `rra_agent.bus.keys` and `rra_agent.bus.config`:

- every wire Struct (each module-level Struct of messages.py, the Structs they contain, and
  `BusConfig`) has a ``#### Name`` section with its ``"t"`` tag and a field table listing
  exactly its fields, in encoding order, with their types and defaults; no section describes
  a Struct that no longer exists;
- every message union (``NodeRequest``...) is listed with exactly its members;
- every public member of `Keys` is in the key table, with the key it really produces;
- the Zenoh session table lists exactly the settings `BusConfig.to_zenoh` makes;
- every byte-level example decodes with our codecs to the message shown next to it, encodes
  back to the same bytes, and its annotation is the one `annotate` generates.

Regenerate the field tables and examples with ``.venv/bin/python tests/test_protocol_doc.py``.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import re
import struct
import sys
import types
import typing
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgspec
import msgspec.inspect as mi
import pytest

from rra_agent.bus import messages as m
from rra_agent.bus.config import BusConfig
from rra_agent.bus.data import decode_data, encode_data
from rra_agent.bus.keys import Keys

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "protocol.md"
ZENOH_TABLE = "<!-- table: zenoh session settings -->"


# ---- what is on the wire ----------------------------------------------------------------
def _module_structs() -> list[type[msgspec.Struct]]:
    return [
        obj
        for obj in vars(m).values()
        if isinstance(obj, type)
        and issubclass(obj, msgspec.Struct)
        and obj.__module__ == m.__name__
        and obj is not m.Msg
    ]


def _reachable(t: mi.Type, out: dict[str, type]) -> None:
    if isinstance(t, mi.StructType):
        if t.cls.__name__ not in out:
            out[t.cls.__name__] = t.cls
            for f in t.fields:
                _reachable(f.type, out)
    elif isinstance(t, mi.UnionType):
        for u in t.types:
            _reachable(u, out)
    elif isinstance(t, mi.ListType | mi.DictType):
        _reachable(t.item_type if isinstance(t, mi.ListType) else t.value_type, out)


def wire_structs() -> dict[str, type[msgspec.Struct]]:
    """Name -> Struct of everything documented: messages, what they contain, BusConfig."""
    out: dict[str, type] = {}
    for cls in [*_module_structs(), BusConfig]:
        _reachable(mi.type_info(cls), out)
    return out


def unions() -> dict[str, list[str]]:
    """The channel unions of messages.py (``X = A | B`` or ``X = A``) -> member class names."""
    out = {}
    for name, obj in vars(m).items():
        if name.startswith("_") or name in ("Any", "T"):
            continue
        if isinstance(obj, types.UnionType):
            args = typing.get_args(obj)
            if all(isinstance(a, type) and issubclass(a, m.Msg) for a in args):
                out[name] = [a.__name__ for a in args]
        elif isinstance(obj, type) and issubclass(obj, m.Msg) and obj.__name__ != name:
            out[name] = [obj.__name__]
    return out


def tag_of(cls: type[msgspec.Struct]) -> str | None:
    tag = cls.__struct_config__.tag
    return tag if isinstance(tag, str) else None


# ---- how the doc renders types and defaults ---------------------------------------------
def render_type(t: mi.Type) -> str:
    match t:
        case mi.StrType():
            return "str"
        case mi.FloatType():
            return "float"
        case mi.BoolType():
            return "bool"
        case mi.IntType():
            return "int"
        case mi.NoneType():
            return "nil"
        case mi.AnyType():
            return "any"
        case mi.BytesType():
            return "bin"
        case mi.ListType(item_type=item):
            return f"array<{render_type(item)}>"
        case mi.DictType(key_type=k, value_type=v):
            return f"map<{render_type(k)}, {render_type(v)}>"
        case mi.LiteralType(values=values):
            return "enum(" + ", ".join(json.dumps(v) for v in values) + ")"
        case mi.UnionType(types=ts):
            return " or ".join(render_type(u) for u in ts)
        case mi.StructType(cls=cls):
            return cls.__name__
    raise AssertionError(f"no doc rendering for {t!r}: extend render_type")


def render_default(f: mi.Field) -> str:
    if f.required:
        return "required"
    value = f.default_factory() if f.default is msgspec.NODEFAULT else f.default
    if isinstance(value, msgspec.Struct):
        return f"{type(value).__name__}()"
    return "nil" if value is None else json.dumps(value)


def field_table(cls: type[msgspec.Struct]) -> str:
    """The markdown table of a Struct's fields (descriptions left empty)."""
    lines = ["| field | type | default | meaning |", "|---|---|---|---|"]
    for f in mi.type_info(cls).fields:
        lines.append(f"| `{f.encode_name}` | {render_type(f.type)} | {render_default(f)} |  |")
    return "\n".join(lines)


def heading(cls: type[msgspec.Struct]) -> str:
    tag = tag_of(cls)
    return f"#### {cls.__name__}" + (f' (`"t": "{tag}"`)' if tag else "")


# ---- the annotated hex dump -------------------------------------------------------------
def _fmt_scalar(b: int, data: bytes, i: int) -> tuple[int, str]:
    """Length and text of a scalar whose marker byte ``b`` is at ``data[i]``."""
    if b <= 0x7F:
        return 1, f"positive fixint {b}"
    if b >= 0xE0:
        return 1, f"negative fixint {b - 0x100}"
    fixed = {
        0xC0: (1, "nil"),
        0xC2: (1, "false"),
        0xC3: (1, "true"),
    }
    if b in fixed:
        return fixed[b]
    ints = {0xCC: ">B", 0xCD: ">H", 0xCE: ">I", 0xCF: ">Q", 0xD0: ">b", 0xD1: ">h", 0xD2: ">i"}
    ints[0xD3] = ">q"
    if b in ints:
        fmt = ints[b]
        n = struct.calcsize(fmt)
        kind = ("uint" if fmt[1].isupper() else "int") + str(8 * n)
        return 1 + n, f"{kind} {struct.unpack_from(fmt, data, i + 1)[0]}"
    if b == 0xCB:
        return 9, f"float64 {struct.unpack_from('>d', data, i + 1)[0]!r}"
    if b == 0xCA:
        return 5, f"float32 {struct.unpack_from('>f', data, i + 1)[0]!r}"
    raise ValueError(f"msgpack marker 0x{b:02x} at {i}: extend annotate")


def _walk(data: bytes, i: int, depth: int, role: str, rows: list[tuple[int, bytes, str]]) -> int:
    """Annotate the msgpack value at ``data[i]``; return the index after it."""
    b = data[i]
    pad = "  " * depth
    lead = f"{role}: " if role else ""
    container = None
    if 0x80 <= b <= 0x8F:
        container, n, head = "map", b & 0x0F, 1
    elif 0x90 <= b <= 0x9F:
        container, n, head = "array", b & 0x0F, 1
    elif b in (0xDC, 0xDE):
        container, n, head = (
            ("array" if b == 0xDC else "map"),
            int.from_bytes(data[i + 1 : i + 3]),
            3,
        )
    if container is not None:
        fmt = ("fix" if head == 1 else "") + container + ("" if head == 1 else "16")
        unit = "pair" if container == "map" else "item"
        rows.append((i, data[i : i + head], f"{pad}{lead}{fmt}, {n} {unit}{'s' * (n != 1)}"))
        j = i + head
        for k in range(n):
            if container == "map":
                j = _walk(data, j, depth + 1, "key", rows)
                j = _walk(data, j, depth + 1, "value", rows)
            else:
                j = _walk(data, j, depth + 1, f"[{k}]", rows)
        return j
    strings = {0xD9: ("str8", 1), 0xDA: ("str16", 2), 0xC4: ("bin8", 1), 0xC5: ("bin16", 2)}
    if 0xA0 <= b <= 0xBF or b in strings:
        fmt, size = ("fixstr", 0) if b <= 0xBF else strings[b]
        n = b & 0x1F if size == 0 else int.from_bytes(data[i + 1 : i + 1 + size])
        start = i + 1 + size
        body = data[start : start + n]
        shown = json.dumps(body.decode()) if "str" in fmt else body.hex()
        if n <= 12:
            rows.append((i, data[i : start + n], f"{pad}{lead}{fmt}({n}) {shown}"))
        else:
            rows.append((i, data[i:start], f"{pad}{lead}{fmt}({n}), the {n} bytes below"))
            for c in range(start, start + n, 12):
                chunk = data[c : min(c + 12, start + n)]
                text = json.dumps(chunk.decode()) if "str" in fmt else chunk.hex()
                rows.append((c, chunk, f"{pad}  {text}"))
        return start + n
    n, text = _fmt_scalar(b, data, i)
    rows.append((i, data[i : i + n], f"{pad}{lead}{text}"))
    return i + n


def annotate(data: bytes, stamp: bool = False) -> str:
    """The doc's annotated dump: ``offset  bytes | meaning``, one msgpack item a line.

    ``stamp``: ``data`` is a send-time attachment (8 bytes, little-endian float64), not msgpack.
    """
    rows: list[tuple[int, bytes, str]] = []
    if stamp:
        (value,) = struct.unpack("<d", data)
        rows.append((0, data, f"float64, little-endian: {value!r} s since the epoch"))
    else:
        end = _walk(data, 0, 0, "", rows)
        assert end == len(data), f"{len(data) - end} trailing bytes"
    width = max(len(chunk.hex(" ")) for _, chunk, _ in rows)
    return "\n".join(f"{off:04x}  {chunk.hex(' '):<{width}} | {text}" for off, chunk, text in rows)


def parse_dump(dump: str) -> bytes:
    """The bytes of an annotated dump; checks each line's offset."""
    out = bytearray()
    for line in dump.strip().splitlines():
        left = line.split(" | ", 1)[0].split()
        assert int(left[0], 16) == len(out), f"wrong offset in {line!r}"
        out.extend(bytes.fromhex("".join(left[1:])))
    return bytes(out)


# ---- reading the doc --------------------------------------------------------------------
@dataclasses.dataclass
class Section:
    name: str
    tag: str | None
    rows: list[list[str]]


_HEADING = re.compile(r'^#### (\w+)(?: \(`"t": "([^"]+)"`\))?\s*$')


def sections(text: str) -> dict[str, Section]:
    out: dict[str, Section] = {}
    current: Section | None = None
    for line in text.splitlines():
        if line.startswith("#"):
            match = _HEADING.match(line)
            current = Section(match[1], match[2], []) if match else None
            if current is not None:
                assert current.name not in out, f"two sections for {current.name}"
                out[current.name] = current
        elif current is not None and line.startswith("| `"):
            current.rows.append([c.strip() for c in line.strip().strip("|").split("|")])
    return out


@dataclasses.dataclass
class Example:
    kind: str
    value: Any
    dump: str


_EXAMPLE = re.compile(
    r"<!-- example: (?P<kind>[\w.]+) -->\s*```json\n(?P<json>.*?)```\s*```text\n(?P<dump>.*?)```",
    re.S,
)


_JSON_EXAMPLE = re.compile(r"<!-- json: (?P<kind>\w+) -->\s*```json\n(?P<json>.*?)```", re.S)


def examples(text: str) -> Iterator[Example]:
    for match in _EXAMPLE.finditer(text):
        yield Example(match["kind"], json.loads(match["json"]), match["dump"])


@pytest.fixture(scope="module")
def doc() -> str:
    return DOC.read_text()


# ---- the tests --------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(wire_structs()))
def test_struct_section_matches_code(doc: str, name: str) -> None:
    cls = wire_structs()[name]
    found = sections(doc).get(name)
    assert found is not None, f"docs/protocol.md has no section `{heading(cls)}`"
    assert found.tag == tag_of(cls), f"{name}: tag in the doc {found.tag!r}, code {tag_of(cls)!r}"
    expected = [
        [f"`{f.encode_name}`", render_type(f.type), render_default(f)]
        for f in mi.type_info(cls).fields
    ]
    documented = [row[:3] for row in found.rows]
    assert documented == expected, (
        f"{name}: the doc's field table is out of date; it should start:\n{field_table(cls)}"
    )
    for row in found.rows:
        assert len(row) == 4 and row[3], f"{name}: field {row[0]} has no meaning column text"


def test_no_section_for_a_struct_that_does_not_exist(doc: str) -> None:
    stale = set(sections(doc)) - set(wire_structs())
    assert not stale, f"docs/protocol.md documents Structs the code lacks: {sorted(stale)}"


def test_every_tag_and_field_name_appears(doc: str) -> None:
    """The brief's minimum, independent of the section layout."""
    for cls in wire_structs().values():
        tag = tag_of(cls)
        if tag is not None:
            assert f'"t": "{tag}"' in doc, f"tag {tag!r} ({cls.__name__}) not in the doc"
        for f in msgspec.structs.fields(cls):
            assert f"`{f.encode_name}`" in doc, f"{cls.__name__}.{f.encode_name} not in the doc"


def test_unions_list_their_members(doc: str) -> None:
    for name, members in unions().items():
        line = f"Union `{name}`: " + ", ".join(f"`{x}`" for x in members) + "."
        assert line in doc, f"docs/protocol.md should contain the line\n{line}"


def _placeholder_call(name: str) -> str:
    """The key a Keys member produces with ``<param>`` placeholders."""
    keys = Keys("P_system")
    member = getattr(Keys, name)
    if isinstance(member, property):
        key = getattr(keys, name)
    else:
        params = list(inspect.signature(member).parameters)[1:]
        key = getattr(keys, name)(*(f"P_{p}" for p in params))
    return re.sub(r"P_(\w+?)(?=/|$)", r"<\1>", key)


def keys_members() -> list[str]:
    fields = {f.name for f in dataclasses.fields(Keys)}
    return [n for n in vars(Keys) if not n.startswith("_") and n not in fields]


@pytest.mark.parametrize("name", keys_members())
def test_keys_member_documented(doc: str, name: str) -> None:
    assert f"`Keys.{name}" in doc, f"Keys.{name} is not in docs/protocol.md"
    if name.startswith("parse_"):
        return
    rows = [line for line in doc.splitlines() if re.search(rf"`Keys\.{name}\b", line)]
    key = _placeholder_call(name)
    assert any(line.startswith(f"| `{key}` |") for line in rows), (
        f"the key table should have a row starting | `{key}` | for Keys.{name}"
    )


class _RecordingConfig:
    def __init__(self) -> None:
        self.settings: dict[str, Any] = {}

    def insert_json5(self, key: str, value: str) -> None:
        self.settings[key] = json.loads(value)


def table_after(doc: str, marker: str) -> list[list[str]]:
    """The body rows of the markdown table right after the line ``marker``."""
    lines = doc.split(f"{marker}\n", 1)[1].splitlines()
    rows = []
    for line in lines[2:]:  # skip the header and the separator
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip().strip("|").split("|")])
    return rows


def test_session_settings_table(doc: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "zenoh", types.SimpleNamespace(Config=_RecordingConfig))
    settings = BusConfig().to_zenoh().settings
    table = {r[0].strip("`"): json.loads(r[1].strip("`")) for r in table_after(doc, ZENOH_TABLE)}
    assert table == settings, "the Zenoh session table differs from BusConfig().to_zenoh()"


_CODECS: dict[str, Any] = {name: getattr(m, name) for name in unions()}


def test_there_are_examples(doc: str) -> None:
    kinds = [e.kind for e in examples(doc)]
    assert {"NodeRequest", "Reply", "data"} <= set(kinds), kinds


def test_examples_decode_to_what_is_shown(doc: str) -> None:
    for ex in examples(doc):
        data = parse_dump(ex.dump)
        if ex.kind == "data":
            assert decode_data(data) == ex.value
            assert encode_data(ex.value) == data
        elif ex.kind == "stamp":
            assert m.unpack_stamp(data) == ex.value
            assert m.pack_stamp(ex.value) == data
        else:
            codec = m.Codec[Any](_CODECS[ex.kind])
            msg = codec.decode(data)
            assert msgspec.to_builtins(msg) == ex.value, f"{ex.kind} example decodes to {msg!r}"
            assert codec.encode(msg) == data, f"{ex.kind} example is not what our Codec encodes"
        dump = annotate(data, stamp=ex.kind == "stamp")
        assert ex.dump.strip() == dump, f"regenerate the {ex.kind} example's annotation:\n{dump}"


def test_json_examples_are_valid(doc: str) -> None:
    found = list(_JSON_EXAMPLE.finditer(doc))
    assert found, "no <!-- json: ... --> example in the doc"
    for match in found:
        cls = wire_structs()[match["kind"]]
        value = msgspec.json.decode(match["json"].encode(), type=cls)
        assert msgspec.to_builtins(value) == json.loads(match["json"]), match["kind"]


def test_annotate_round_trips_every_marker_it_knows() -> None:
    value = {
        "s": "x" * 40,
        "b": b"\x00\x01",
        "n": None,
        "f": False,
        "i": [0, -1, 200, 70000, -200, 1.5, 2**40, -(2**40)],
        "m": {"k": [True]},
    }
    data = msgspec.msgpack.encode(value)
    assert parse_dump(annotate(data)) == data


if __name__ == "__main__":  # print the tables and examples to paste into docs/protocol.md
    for cls in wire_structs().values():
        print(heading(cls), "", field_table(cls), "", sep="\n")
    for name, members in unions().items():
        print(f"Union `{name}`: " + ", ".join(f"`{x}`" for x in members) + ".")
    for arg in sys.argv[1:]:  # e.g. 'NodeRequest={"t": "describe"}'
        kind, _, text = arg.partition("=")
        value = json.loads(text)
        if kind == "data":
            data = encode_data(value)
        elif kind == "stamp":
            data = m.pack_stamp(value)
        else:
            codec = m.Codec[Any](_CODECS[kind])
            data = codec.encode(codec.decode(msgspec.msgpack.encode(value)))
        dump = annotate(data, stamp=kind == "stamp")
        print(f"<!-- example: {kind} -->\n```json\n{text}\n```\n```text\n{dump}\n```")
