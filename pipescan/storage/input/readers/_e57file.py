"""An E57 file's own layout, checked by pipescan before libE57 opens it.

libE57 parses the file's XML with Xerces, which loads an external DTD the XML names and expands
its entities (a file could make it read local files and send them to a server), and which
recurses once per nesting level (200,000 nested elements crash the process). It also lets many
scans point at one binary section, so a small file can declare a billion points. So the XML is
read here first, page by page (each 1 KiB page ends in a 4-byte checksum), and parsed with
expat, which does not recurse, with every declaration refused:

- a ``<!DOCTYPE``, any entity declaration or reference to an external entity, and an
  ``xsi:schemaLocation`` (a schema to fetch) are refused;
- elements may nest at most :data:`XML_MAX_DEPTH` deep, and the XML is at most
  ``metadata_max_bytes`` long;
- every binary section (a ``CompressedVector``'s points, a ``Blob``) lies inside the file, no
  two overlap, and a ``CompressedVector``'s ``recordCount`` records of its prototype's bits fit
  in its section's length.
"""

from __future__ import annotations

import itertools
import math
import struct
from dataclasses import dataclass, field
from pathlib import Path
from xml.parsers import expat

from pipescan.storage.input.readers._common import Where

XML_MAX_DEPTH = 64
"""Elements nested deeper than this are refused: the E57 standard's tree is about 10 deep."""
PAGE_BYTES = 1024
PAGE_DATA_BYTES = 1020  # the last 4 bytes of a page are its CRC-32C
_HEADER = struct.Struct("<8sIIQQQQ")  # signature, major, minor, length, XML offset/length, page
_SECTION = struct.Struct("<B7sQQQ")  # id, reserved, logical length, data and index offsets
_COMPRESSED_VECTOR_SECTION = 1
_READ_BLOCK = 1 << 20
_DEFAULT_INTEGER = (-(2**63), 2**63 - 1)
_SECTION_KINDS = ("CompressedVector", "Blob")
_MAX_KEPT_NODES = 100_000  # elements inside point prototypes: a scan has a few dozen fields
_DECLARED_HINT = (
    "the file was not written by an E57 exporter: export it again from the scan software"
)


class _Refused(Exception):
    """Raised inside the expat handlers; carries the reason and the field."""

    def __init__(self, reason: str, field: str = "XML", *, declared: bool = False) -> None:
        super().__init__(reason)
        self.reason, self.field, self.declared = reason, field, declared


@dataclass
class _Node:
    name: str
    type: str
    attrs: dict[str, str]
    children: list[_Node] = field(default_factory=list)  # kept inside a section's element only
    path: str = ""
    seen: dict[str, int] = field(default_factory=dict)  # children by name, for their paths
    keep: bool = False  # a section's element (CompressedVector, Blob) or inside one


@dataclass(frozen=True)
class Section:
    """A binary section the XML points at: where, and what it must hold."""

    path: str  # where in the XML, for errors: "/data3D/vectorChild[1]/points"
    kind: str  # "CompressedVector" or "Blob"
    offset: int  # physical offset in the file
    record_count: int  # records of a CompressedVector (0 for a Blob)
    record_bits: int  # bits of one record, at least (0 for a Blob)
    blob_length: int  # a Blob's length in bytes (0 for a CompressedVector)


def physical(logical: int) -> int:
    """The file offset of a logical byte offset (the pages' checksums skipped)."""
    return (logical // PAGE_DATA_BYTES) * PAGE_BYTES + logical % PAGE_DATA_BYTES


def logical_of(physical_offset: int) -> int:
    return (physical_offset // PAGE_BYTES) * PAGE_DATA_BYTES + min(
        physical_offset % PAGE_BYTES, PAGE_DATA_BYTES
    )


def _read_logical(fh, start_physical: int, length: int, size: int) -> bytes:
    """``length`` logical bytes from a physical offset, the checksums left out."""
    out = bytearray()
    pos = start_physical
    while len(out) < length:
        in_page = pos % PAGE_BYTES
        if in_page >= PAGE_DATA_BYTES or pos >= size:
            raise _Refused("the XML section runs past the end of the file", "header")
        take = min(PAGE_DATA_BYTES - in_page, length - len(out))
        fh.seek(pos)
        got = fh.read(take)
        if len(got) != take:
            raise _Refused("the XML section runs past the end of the file", "header")
        out += got
        pos = (pos // PAGE_BYTES + 1) * PAGE_BYTES
    return bytes(out)


def _bits(node: _Node) -> int:
    """The fewest bits a record of this prototype node takes (E57's bit-packing)."""
    kind = node.type
    if kind == "Float":
        return 32 if node.attrs.get("precision") == "single" else 64
    if kind in ("Integer", "ScaledInteger"):
        try:
            lo = int(node.attrs.get("minimum", _DEFAULT_INTEGER[0]))
            hi = int(node.attrs.get("maximum", _DEFAULT_INTEGER[1]))
        except ValueError as exc:
            raise _Refused(f"{node.path} has a minimum or maximum that is not an integer") from exc
        span = hi - lo + 1
        return math.ceil(math.log2(span)) if span > 1 else 0
    if kind == "String":
        return 8  # at least its one-byte length prefix
    return sum(_bits(child) for child in node.children)  # Structure, Vector


class _Parser:
    """Builds the element tree with expat, refusing declarations, external references and
    depth past the bound as they come."""

    def __init__(self) -> None:
        p = expat.ParserCreate(encoding="UTF-8")  # the standard's encoding, whatever is declared
        p.SetParamEntityParsing(expat.XML_PARAM_ENTITY_PARSING_NEVER)
        p.StartDoctypeDeclHandler = self._doctype
        p.EntityDeclHandler = self._entity
        p.UnparsedEntityDeclHandler = self._entity
        p.NotationDeclHandler = self._entity
        p.ExternalEntityRefHandler = self._external
        p.StartElementHandler = self._start
        p.EndElementHandler = self._end
        self.parser = p
        self.stack: list[_Node] = []
        self.root: _Node | None = None
        self.sections: list[_Node] = []
        self.kept = 0

    def _doctype(self, name, *args) -> None:
        raise _Refused(
            f"the XML has a <!DOCTYPE {name}> declaration (a DTD can make the XML parser fetch "
            "files or URLs), which E57 files do not use",
            declared=True,
        )

    def _entity(self, name, *args) -> None:
        raise _Refused(
            f"the XML declares an entity or notation {name!r}, which E57 files do not use",
            declared=True,
        )

    def _external(self, *args) -> int:
        raise _Refused(
            "the XML refers to an external entity, which E57 files do not use", declared=True
        )

    def _start(self, name: str, attrs: dict[str, str]) -> None:
        if len(self.stack) >= XML_MAX_DEPTH:
            raise _Refused(f"the XML nests elements more than {XML_MAX_DEPTH} deep")
        for key in attrs:
            if key.rsplit(":", 1)[-1].lower() in ("schemalocation", "nonamespaceschemalocation"):
                raise _Refused(
                    f"the XML names a schema to load ({key}), which E57 files do not use",
                    declared=True,
                )
        local = name.rsplit(" ", 1)[-1].rsplit(":", 1)[-1]
        parent = self.stack[-1] if self.stack else None
        kind = attrs.get("type", "")
        if parent is None:
            node = _Node(local, kind, {}, path="")
            self.root = node
        else:
            same = parent.seen.get(local, 0)
            parent.seen[local] = same + 1
            path = f"{parent.path}/{local}" + (f"[{same}]" if local == "vectorChild" else "")
            keep = parent.keep or kind in _SECTION_KINDS
            # Only a section's element and what is inside it are kept (for its records' bits):
            # memory stays with the depth, whatever the XML's length.
            node = _Node(local, kind, dict(attrs) if keep else {}, path=path, keep=keep)
            if keep:
                self.kept += 1
                if self.kept > _MAX_KEPT_NODES:
                    raise _Refused(f"the XML's point prototypes hold over {_MAX_KEPT_NODES:,} "
                                   "elements")  # fmt: skip
                if parent.keep:
                    parent.children.append(node)
        self.stack.append(node)

    def _end(self, name: str) -> None:
        node = self.stack.pop()
        if node.type in _SECTION_KINDS:
            self.sections.append(node)

    def feed(self, data: bytes, final: bool) -> None:
        try:
            self.parser.Parse(data, final)
        except expat.ExpatError as exc:
            raise _Refused(f"the XML is not well formed ({expat.ErrorString(exc.code)}, line "
                           f"{exc.lineno})") from None  # fmt: skip


def _sections(nodes: list[_Node]) -> list[Section]:
    found: list[Section] = []
    for node in nodes:
        try:
            offset = int(node.attrs["fileOffset"])
            if node.type == "CompressedVector":
                count = int(node.attrs.get("recordCount", "0"))
                prototype = next((c for c in node.children if c.name == "prototype"), None)
                bits = 0 if prototype is None else _bits(prototype)
                found.append(Section(node.path, node.type, offset, count, bits, 0))
            else:
                found.append(Section(node.path, node.type, offset, 0, 0, int(node.attrs["length"])))
        except (KeyError, ValueError) as exc:
            raise _Refused(f"{node.path} has no valid fileOffset, recordCount or length",
                           node.path) from exc  # fmt: skip
    return found


def _check_sections(fh, sections: list[Section], size: int) -> None:
    """Each section inside the file, none overlapping another, and a CompressedVector's
    records within its section's length."""
    extents = []
    for s in sections:
        if s.offset < 0 or s.offset % PAGE_BYTES >= PAGE_DATA_BYTES:
            raise _Refused(f"{s.path}'s fileOffset {s.offset} is not a data offset", s.path)
        if s.kind == "Blob":
            length = s.blob_length + 16  # the blob section's header
        else:
            if s.record_count < 0:
                raise _Refused(f"{s.path} declares {s.record_count} records", s.path)
            if s.record_count == 0:
                continue  # libE57 writes no section for an empty scan
            if s.offset + _SECTION.size > size:
                raise _Refused(f"{s.path}'s section lies outside the file", s.path)
            fh.seek(s.offset)
            ident, _, length, _, _ = _SECTION.unpack(fh.read(_SECTION.size))
            if ident != _COMPRESSED_VECTOR_SECTION:
                raise _Refused(f"{s.path} does not point at a compressed-vector section", s.path)
            if s.record_bits == 0:
                raise _Refused(f"{s.path}'s records take no bits: its {s.record_count:,} points "
                               "would hold no data", s.path)  # fmt: skip
            if s.record_count * s.record_bits > 8 * length:
                raise _Refused(
                    f"{s.path} declares {s.record_count:,} records of {s.record_bits} bits, but "
                    f"its section holds {length:,} bytes", s.path,
                )  # fmt: skip
        end = physical(logical_of(s.offset) + length)
        if end > size:
            raise _Refused(f"{s.path}'s section of {length:,} bytes runs past the end of the "
                           "file", s.path)  # fmt: skip
        extents.append((s.offset, len(extents), end, s.path))
    extents.sort()
    for (_, _, end, first), (start, _, _, second) in itertools.pairwise(extents):
        if start < end:
            raise _Refused(
                f"{second} shares its binary section with {first} (each scan must have its own)",
                second,
            )


def check_layout(path: Path, where: Where) -> None:
    """Refuse an E57 file whose XML holds a declaration, an external reference or nests past
    :data:`XML_MAX_DEPTH`, or whose binary sections overlap, lie outside the file or hold fewer
    bytes than their records take. Reads the XML in blocks (never more than
    ``metadata_max_bytes``); nothing is allocated for the points.

    Raises
    ------
    PointFileError
        Naming the file and the field (``XML``, ``header`` or the section's XML path).
    """
    try:
        with path.open("rb") as fh:
            size = fh.seek(0, 2)
            fh.seek(0)
            head = fh.read(_HEADER.size)
            if len(head) < _HEADER.size or not head.startswith(b"ASTM-E57"):
                raise _Refused("the file does not start with an E57 header", "header")
            _, _, _, declared, xml_offset, xml_length, page = _HEADER.unpack(head)
            if page != PAGE_BYTES:
                raise _Refused(f"the header declares pages of {page} bytes, not 1024", "header")
            if declared != size:
                raise _Refused(f"the header declares {declared:,} bytes, the file holds "
                               f"{size:,}: it is truncated", "header")  # fmt: skip
            if xml_length > where.limits.metadata_max_bytes:
                what = f"the XML section is {xml_length:,} bytes"
                raise where.over("metadata_max_bytes", what, field="XML")
            parser = _Parser()
            done = 0
            while done < xml_length:
                take = min(_READ_BLOCK, xml_length - done)
                start = physical(logical_of(xml_offset) + done)
                parser.feed(_read_logical(fh, start, take, size), final=False)
                done += take
            parser.feed(b"", final=True)
            if parser.root is None:
                raise _Refused("the XML has no root element")
            _check_sections(fh, _sections(parser.sections), size)
    except _Refused as exc:
        if exc.declared:
            raise where.error(exc.reason, field=exc.field, hint=_DECLARED_HINT) from None
        raise where.corrupt(f"cannot read E57: {exc.reason}", field=exc.field) from None
    except OSError as exc:
        raise where.corrupt(f"cannot read the file: {exc}") from exc
