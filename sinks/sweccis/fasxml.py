"""The ground rules of SWECCIS FAS documents: namespace, version, values, and safe parsing.

Shared by the document encoders (``sinks.sweccis.fas``) and the order decoder
(``sinks.sweccis.order``). Writing checks every value against what the schema
(``schemas/sweccis-fas.xsd``) allows and raises ``ValueError`` naming the field, so a
value the schema cannot hold is refused rather than sent as something it is not. Reading
goes through defusedxml (no DTDs, entities or external references) within a byte bound, and
every problem is a ``DocumentError`` naming the element.
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from datetime import UTC, datetime
from enum import StrEnum
from importlib.resources import files

from defusedxml import DefusedXmlException
from defusedxml.ElementTree import fromstring

from gateway.errors import Malformed

__all__ = [
    "MAX_DOCUMENT_BYTES",
    "NAMESPACE",
    "SCHEMA_VERSION",
    "SCHEMA_VERSIONS",
    "DocumentError",
    "Fas",
    "Node",
    "add",
    "check_id",
    "check_text",
    "clean_text",
    "load_schema",
    "number",
    "parse_root",
    "tag_of",
    "time_text",
    "to_bytes",
]

#: The namespace of every version 1 document; its last part is the schema version.
NAMESPACE = "urn:fischer-gateway:sweccis:fas:1"
#: The ``version`` attribute a root element carries by default (version 1, the first).
SCHEMA_VERSION = "1"
#: Every version written and read, and its namespace. Version 2 adds the track status
#: ``merged`` and its ``MergedInto``; everything else is version 1's shape.
SCHEMA_VERSIONS = {"1": NAMESPACE, "2": "urn:fischer-gateway:sweccis:fas:2"}
_NAMESPACES = frozenset(SCHEMA_VERSIONS.values())
#: The largest document read or written unless configured otherwise.
MAX_DOCUMENT_BYTES = 65_536
_SCHEMA_RESOURCES = {"1": "schemas/sweccis-fas.xsd", "2": "schemas/sweccis-fas-2.xsd"}
_ID = re.compile(r"[!-~]{1,200}")
# Characters XML 1.0 cannot carry at all (control characters, lone surrogates, U+FFFE/F).
_NOT_XML = re.compile("[^\t\n\r\x20-\ud7ff\ue000-\ufffd\U00010000-\U0010ffff]")
_DECLARATION = re.compile(rb"<\?xml[^>]*?encoding=[\"']([A-Za-z0-9._-]+)[\"']")


class Fas(StrEnum):
    """The Functional Area Services: the root element of each kind of data document."""

    INTEL = "Intel"
    LOGISTICS = "Logistics"
    OPERATIONS = "Operations"
    ORDERS = "Orders"


class DocumentError(Malformed):
    """Raised for a document that is not one we accept; ``element`` names where.

    ``doc_id`` is the document's id when it could be read, so the sender can be told which
    document was rejected.
    """

    reason = "invalid"

    def __init__(self, element: str, message: str, *, doc_id: str | None = None) -> None:
        self.element = element
        self.doc_id = doc_id
        super().__init__(f"{element}: {message}")


def load_schema(version: str = SCHEMA_VERSION) -> bytes:
    """The XSD of every document of ``version`` (``schemas/sweccis-fas.xsd`` for 1,
    ``sweccis-fas-2.xsd`` for 2), from package data; ``ValueError`` for another version."""
    resource = _SCHEMA_RESOURCES.get(version)
    if resource is None:
        raise ValueError(
            f"SWECCIS FAS version {version!r} is not one of {sorted(_SCHEMA_RESOURCES)}"
        )
    data: bytes = files("sinks.sweccis").joinpath(resource).read_bytes()
    return data


# -- writing ---------------------------------------------------------------------------------


def check_text(value: str, field: str, max_length: int, *, min_length: int = 0) -> str:
    """``value`` if XML can carry it in ``min_length..max_length`` characters, else ValueError."""
    if not min_length <= len(value) <= max_length:
        raise ValueError(f"{field}: {len(value)} characters, expected {min_length} to {max_length}")
    if _NOT_XML.search(value):
        raise ValueError(f"{field}: holds a character XML cannot carry")
    return value


def clean_text(value: str, max_length: int) -> str:
    """``value`` cut to ``max_length`` with each character XML cannot carry replaced by U+FFFD
    (for free text of our own, such as a rejection's reason, which must always be sendable)."""
    return _NOT_XML.sub("\ufffd", value[:max_length])


def check_id(value: str, field: str) -> str:
    """``value`` if it is a document id (1..200 printable ASCII, no spaces); else ``ValueError``."""
    if not _ID.fullmatch(value):
        raise ValueError(f"{field}: {value[:40]!r} is not 1 to 200 printable ASCII characters")
    return value


def number(value: float, field: str, low: float | None = None, high: float | None = None) -> str:
    """``value`` as an xs:double; ``ValueError`` when not finite or outside ``low..high``."""
    if not math.isfinite(value):
        raise ValueError(f"{field}: {value} is not a finite number")
    if (low is not None and value < low) or (high is not None and value > high):
        raise ValueError(f"{field}: {value} is outside {low}..{high}")
    return repr(float(value))


def time_text(value: datetime) -> str:
    """UTC, ISO 8601, millisecond precision, ``Z``: ``2026-11-22T12:00:00.000Z``."""
    return value.astimezone(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def add(parent: ET.Element, tag: str, text: str | None = None, **attrs: str | None) -> ET.Element:
    """A child ``tag`` of ``parent`` with ``text`` and the attributes that are not None."""
    child = ET.SubElement(parent, tag, {k: v for k, v in attrs.items() if v is not None})
    if text is not None:
        child.text = text
    return child


def to_bytes(root: ET.Element) -> bytes:
    """The document as UTF-8, its root in the namespace of its ``version`` attribute (no
    declaration: UTF-8 is the rule)."""
    root.set("xmlns", SCHEMA_VERSIONS[root.get("version", SCHEMA_VERSION)])
    data: bytes = ET.tostring(root, encoding="utf-8", xml_declaration=False)
    return data


# -- reading ---------------------------------------------------------------------------------


def tag_of(element: ET.Element, where: str, namespace: str | None = None) -> str:
    """The local name of ``element``; ``DocumentError`` if it is not in ``namespace`` (any
    of our versions' when None)."""
    found, brace, local = element.tag[1:].partition("}")
    allowed = _NAMESPACES if namespace is None else frozenset({namespace})
    if not element.tag.startswith("{") or not brace or found not in allowed:
        expected = " or ".join(sorted(allowed))
        raise DocumentError(where, f"<{element.tag}> is not in namespace {expected}")
    return local


def _namespace(element: ET.Element) -> str:
    return element.tag[1:].partition("}")[0]


def parse_root(data: bytes, max_bytes: int = MAX_DOCUMENT_BYTES) -> tuple[ET.Element, str]:
    """Parse one document within ``max_bytes``; its root element and that element's name.

    Raises ``DocumentError`` for too many bytes, a declared encoding other than UTF-8, XML
    that is not well formed (or holds a DTD or entities), another namespace or version.
    """
    if len(data) > max_bytes:
        raise DocumentError("(document)", f"{len(data)} bytes, more than {max_bytes}")
    if not data.strip():
        raise DocumentError("(document)", "empty")
    declared = _DECLARATION.match(data.lstrip())
    if declared and declared.group(1).lower() not in (b"utf-8", b"utf8"):
        raise DocumentError("(document)", "the encoding must be UTF-8")
    try:
        root = fromstring(data, forbid_dtd=True, forbid_entities=True, forbid_external=True)
    except DefusedXmlException:
        raise DocumentError(
            "(document)", "DTDs, entities and external references are refused"
        ) from None
    except (ET.ParseError, ValueError, LookupError) as exc:
        raise DocumentError("(document)", f"not well-formed XML ({exc})") from None
    name = tag_of(root, "(root)")
    version = root.get("version")
    if version is None or SCHEMA_VERSIONS.get(version) != _namespace(root):
        raise DocumentError(
            f"{name}/@version",
            f"{version!r} is not the version of namespace {_namespace(root)}"
            f" ({', '.join(f'{v} for {n}' for v, n in SCHEMA_VERSIONS.items())})",
        )
    return root, name


_DOUBLE = re.compile(r"[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?")
_TIME = re.compile(r"(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d)(\.\d+)?(Z|[+-]\d\d:\d\d)")


class Node:
    """One element being read, with its path for error messages (``Orders/FiveLineOrder``).

    Every accessor checks what the schema says and raises ``DocumentError`` naming the
    element or attribute, carrying the document's id when known.
    """

    __slots__ = ("doc_id", "element", "path")

    def __init__(self, element: ET.Element, path: str, doc_id: str | None = None) -> None:
        self.element = element
        self.path = path
        self.doc_id = doc_id

    def fail(self, message: str, attribute: str | None = None) -> DocumentError:
        """The error for this element (or one of its attributes)."""
        where = self.path if attribute is None else f"{self.path}/@{attribute}"
        return DocumentError(where, message, doc_id=self.doc_id)

    def children(self, allowed: dict[str, int]) -> dict[str, list[Node]]:
        """The child elements by name; each at most ``allowed[name]`` times, no others."""
        found: dict[str, list[Node]] = {}
        for child in self.element:
            name = tag_of(child, self.path, _namespace(self.element))
            if name not in allowed:
                raise self.fail(f"unexpected element <{name}>")
            nodes = found.setdefault(name, [])
            if len(nodes) >= allowed[name]:
                raise self.fail(f"<{name}> more than {allowed[name]} times")
            nodes.append(Node(child, f"{self.path}/{name}", self.doc_id))
        return found

    def check_attributes(self, allowed: frozenset[str]) -> None:
        """Refuse attributes the schema does not list for this element."""
        for name in self.element.attrib:
            if name not in allowed:
                raise self.fail("unexpected attribute", name)

    def text(self, *, max_length: int, min_length: int = 0) -> str:
        """The element's text (it may have no child elements), within the bounds."""
        if len(self.element):
            raise self.fail("expected text, found child elements")
        value = self.element.text or ""
        if not min_length <= len(value) <= max_length:
            raise self.fail(f"expected {min_length} to {max_length} characters, got {len(value)}")
        return value

    def attribute(self, name: str) -> str | None:
        """The attribute's value, or None when absent."""
        return self.element.get(name)

    def required(self, name: str) -> str:
        """The attribute's value; ``DocumentError`` when absent."""
        value = self.element.get(name)
        if value is None:
            raise self.fail("is required", name)
        return value

    def double(self, name: str, low: float, high: float) -> float | None:
        """An optional xs:double attribute within ``low..high`` (no NaN, no infinity)."""
        value = self.element.get(name)
        return None if value is None else self._double(value, name, low, high)

    def required_double(self, name: str, low: float, high: float) -> float:
        """A required xs:double attribute within ``low..high``."""
        return self._double(self.required(name), name, low, high)

    def _double(self, value: str, name: str, low: float, high: float) -> float:
        if not _DOUBLE.fullmatch(value.strip()):
            raise self.fail(f"{value[:40]!r} is not a decimal number", name)
        number = float(value)
        if not low <= number <= high:
            raise self.fail(f"{number} is outside {low}..{high}", name)
        return number

    def time(self, name: str) -> datetime | None:
        """An optional xs:dateTime attribute with its zone, in UTC."""
        value = self.element.get(name)
        return None if value is None else self._time(value, name)

    def text_time(self) -> datetime:
        """The element's text as an xs:dateTime with its zone, in UTC."""
        return self._time(self.text(max_length=64), None)

    def _time(self, value: str, name: str | None) -> datetime:
        match = _TIME.fullmatch(value.strip())
        if match is None:
            raise self.fail(f"{value[:40]!r} is not a date and time with a zone", name)
        whole, fraction, zone = match.groups()
        # Python reads at most microseconds; finer digits are cut, not rounded into the next second.
        fraction = (fraction or ".0")[:7]
        try:
            parsed = datetime.fromisoformat(whole + fraction + zone.replace("Z", "+00:00"))
            return parsed.astimezone(UTC)
        except (ValueError, OverflowError) as exc:
            raise self.fail(f"{value[:40]!r} is not a valid date and time ({exc})", name) from None
