"""A SWECCIS server for tests: real TLS on loopback, 4-byte length frames, the shipped XSD.

``SweccisPeer`` listens on 127.0.0.1 with TLS from its own trustme CA and requires a client
certificate from that CA (a missing or foreign one is refused at the handshake). Its framing
is written here, independently of ``gateway.transports.frames``: a 4-byte big-endian length,
then the document; a frame over ``max_frame_bytes`` closes the connection. Every document is
parsed by lxml (no entities, no network) and validated against the shipped XSD; one that
fails is recorded in ``invalid`` and, if it has an id, acknowledged ``rejected`` with the
schema's message.

A client must ``Register`` first; the peer answers ``Registered`` with what it asked for
(less ``withhold``), or a rejected ``Ack`` when ``refuse_registration`` is set. Data
documents (Intel, Logistics, Operations, and the gateway's OrderStatus of the Orders FAS) of
a registered FAS are recorded in ``accepted`` by
id and acknowledged ``accepted``; an id seen before gets ``duplicate``; ids in ``reject`` get
``rejected`` with the given reason. Knobs: ``is_down`` (connections are closed at once),
``drop_acks`` (that many documents are recorded but never acknowledged), ``noise`` (raw
bytes written before each acknowledgement: a garbage frame, an oversize header).

Orders go the other way: ``push_order`` sends an ``Orders`` document to every connection
registered for Orders and keeps it in ``outbox`` until the client acknowledges it (any
status; the acks are in ``order_acks``); a client that registers for Orders gets the whole
outbox, as a server re-sends what was never acknowledged. ``order_document`` builds a valid
one.

Async (``async with SweccisPeer(tmp_path) as peer``) or from a sync test, in a thread
(``with SweccisPeer(tmp_path).in_thread() as peer``, then ``peer.call(peer.push_order, ...)``).
"""

from __future__ import annotations

import ssl
import struct
from collections.abc import Awaitable, Callable, Iterator, Mapping
from contextlib import AsyncExitStack, contextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

import anyio
import anyio.abc
import trustme
from anyio.from_thread import BlockingPortal, start_blocking_portal
from anyio.streams.buffered import BufferedByteReceiveStream
from https_peer import AlertingTLSStream
from lxml import etree

from sinks.sweccis.fasxml import NAMESPACE, SCHEMA_VERSIONS, load_schema

NS = f"{{{NAMESPACE}}}"
#: FAS version by namespace: the peer answers each document in its own version.
VERSION_OF = {namespace: version for version, namespace in SCHEMA_VERSIONS.items()}
DATA_FAS = ("Intel", "Logistics", "Operations")
#: Data documents by root element, and the FAS a client must have registered to publish them.
DATA_ROOTS = {**{fas: fas for fas in DATA_FAS}, "OrderStatus": "Orders"}
_PARSER = etree.XMLParser(resolve_entities=False, no_network=True, load_dtd=False)


@dataclass
class Received:
    """One document the peer read: its root name, id (or ref) and the status answered."""

    root: str
    doc_id: str | None
    status: str | None
    """accepted, duplicate, rejected; None: not acknowledged (dropped, or not a data document)."""


@dataclass
class Connection:
    """One client connection: what it registered and a lock so frames never interleave."""

    stream: anyio.abc.ByteStream
    publish: set[str] = field(default_factory=set)
    subscribe: set[str] = field(default_factory=set)
    lock: anyio.Lock = field(default_factory=anyio.Lock)

    async def send(self, payload: bytes) -> None:
        async with self.lock:
            await self.stream.send(struct.pack(">I", len(payload)) + payload)


def _ack(ref: str, status: str, reason: str | None = None, namespace: str = NAMESPACE) -> bytes:
    ns, version = f"{{{namespace}}}", VERSION_OF[namespace]
    root = etree.Element(
        f"{ns}Ack", nsmap={None: namespace}, version=version, ref=ref, status=status
    )
    if reason is not None:
        etree.SubElement(root, f"{ns}Reason").text = reason[:512]
    return bytes(etree.tostring(root, xml_declaration=True, encoding="UTF-8"))


def order_document(doc_id: str, order_id: str, **fields: Any) -> bytes:
    """A valid ``Orders`` document. Fields: ``task`` (observe_point), ``point`` (lat, lon)
    or ``mgrs`` or ``polygon`` (list of (lat, lon)), ``priority``, ``airframe``, ``issuer``,
    ``time`` (2026-11-22T12:00:00Z), ``not_before``/``not_after``, ``target``, ``track_id``,
    ``reporting``, ``measures`` (list of str)."""
    root = etree.Element(f"{NS}Orders", nsmap={None: NAMESPACE}, version="1", id=doc_id)
    body = etree.SubElement(root, f"{NS}FiveLineOrder")

    def add(parent: Any, tag: str, text: str | None = None, **attrs: str) -> Any:
        child = etree.SubElement(parent, f"{NS}{tag}", **attrs)
        child.text = text
        return child

    add(body, "OrderId", order_id)
    if "issuer" in fields:
        add(body, "Issuer", fields["issuer"])
    add(body, "Time", fields.get("time", "2026-11-22T12:00:00Z"))
    if "airframe" in fields:
        add(body, "Airframe", fields["airframe"])
    add(body, "Task", fields.get("task", "observe_point"))
    location = add(body, "Location")
    if "mgrs" in fields:
        add(location, "Mgrs", fields["mgrs"])
    elif "polygon" in fields:
        polygon = add(location, "Polygon")
        for lat, lon in fields["polygon"]:
            add(polygon, "Corner", latDeg=str(lat), lonDeg=str(lon))
    else:
        lat, lon = fields.get("point", (65.8252, 21.6886))
        add(location, "Point", latDeg=str(lat), lonDeg=str(lon))
    window = {
        k: fields[f]
        for k, f in (("notBefore", "not_before"), ("notAfter", "not_after"))
        if f in fields
    }
    if window:
        add(body, "Window", **window)
    if "target" in fields or "track_id" in fields:
        attrs = {"trackId": fields["track_id"]} if "track_id" in fields else {}
        add(body, "Target", fields.get("target"), **attrs)
    if "priority" in fields:
        add(body, "Priority", fields["priority"])
    if "reporting" in fields:
        add(body, "Reporting", fields["reporting"])
    if "measures" in fields:
        measures = add(body, "ControlMeasures")
        for measure in fields["measures"]:
            add(measures, "Measure", measure)
    return bytes(etree.tostring(root, xml_declaration=True, encoding="UTF-8"))


class SweccisPeer:
    """A SWECCIS server's FAS endpoint over real TLS with client certificates."""

    def __init__(
        self,
        directory: Path,
        *,
        reject: Mapping[str, str] | None = None,
        refuse_registration: str | None = None,
        withhold: frozenset[str] = frozenset(),
        drop_acks: int = 0,
        noise: bytes | None = None,
        max_frame_bytes: int = 1 << 20,
        server_name: str = "127.0.0.1",
    ) -> None:
        self.directory = directory
        self.reject = dict(reject or {})
        self.refuse_registration = refuse_registration
        self.withhold = withhold
        self.drop_acks = drop_acks
        self.noise = noise
        self.max_frame_bytes = max_frame_bytes
        self.is_down = False
        self.ca = trustme.CA()
        self.server_cert = self.ca.issue_cert(server_name)
        client = self.ca.issue_cert("fischer-gateway")
        directory.mkdir(parents=True, exist_ok=True)
        self.ca_file = directory / "sweccis-ca.pem"
        self.cert_file = directory / "sweccis-client.pem"
        self.key_file = directory / "sweccis-client.key"
        self.ca.cert_pem.write_to_path(str(self.ca_file))
        for blob in client.cert_chain_pems:
            blob.write_to_path(str(self.cert_file), append=True)
        client.private_key_pem.write_to_path(str(self.key_file))
        self.port = 0
        self.schema = etree.XMLSchema(etree.fromstring(load_schema()))
        #: Each version's schema by namespace; a document is checked against its own.
        self.schemas = {
            namespace: etree.XMLSchema(etree.fromstring(load_schema(version)))
            for version, namespace in SCHEMA_VERSIONS.items()
        }
        #: Data documents accepted, by id, in arrival order (each id once).
        self.accepted: dict[str, etree._Element] = {}
        #: Every document read, in arrival order, with the status answered.
        self.documents: list[Received] = []
        #: Schema or syntax failures: (document id or None, message).
        self.invalid: list[tuple[str | None, str]] = []
        #: Each Register: (client, publish, subscribe).
        self.registrations: list[tuple[str, list[str], list[str]]] = []
        #: Acks of our orders: (ref, status, reason).
        self.order_acks: list[tuple[str, str, str | None]] = []
        #: Orders not acknowledged yet, by document id.
        self.outbox: dict[str, bytes] = {}
        self.connections: list[Connection] = []
        self.connection_count = 0
        self.handshake_failures: list[str] = []
        self._stack: AsyncExitStack | None = None
        self._portal: BlockingPortal | None = None

    # -- what tests and configs need ------------------------------------------------------------

    @property
    def uri(self) -> str:
        """Where the client connects: ``tls://127.0.0.1:PORT``."""
        return f"tls://127.0.0.1:{self.port}"

    def link_options(self, **extra: Any) -> dict[str, Any]:
        """Options of a ``sweccis`` sink or source that trusts this peer and is trusted by it."""
        return {
            "uri": self.uri,
            "ca_file": str(self.ca_file),
            "cert_file": str(self.cert_file),
            "key_file": str(self.key_file),
            **extra,
        }

    def order_statuses(self, order_id: str) -> list[str]:
        """The statuses of ``order_id`` the server accepted, in arrival order."""
        return [
            doc.findtext(f"{NS}Status") or ""
            for doc in self.of("OrderStatus")
            if doc.findtext(f"{NS}OrderId") == order_id
        ]

    def of(self, root: str) -> list[etree._Element]:
        """The accepted documents whose root element is ``root`` (Intel, Logistics ...)."""
        return [doc for doc in self.accepted.values() if etree.QName(doc).localname == root]

    def server_context(self) -> ssl.SSLContext:
        """TLS for the listener: our server certificate, client certificates required."""
        context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        context.verify_mode = ssl.CERT_REQUIRED
        self.server_cert.configure_cert(context)
        self.ca.configure_trust(context)
        return context

    # -- lifetime -------------------------------------------------------------------------------

    async def __aenter__(self) -> SweccisPeer:
        async with AsyncExitStack() as stack:
            listener = await anyio.create_tcp_listener(local_host="127.0.0.1", local_port=0)
            await stack.enter_async_context(listener)
            self.port = int(listener.extra(anyio.abc.SocketAttribute.local_port))
            tg = await stack.enter_async_context(anyio.create_task_group())
            context = self.server_context()
            tg.start_soon(listener.serve, lambda stream: self._serve(stream, context))
            stack.callback(tg.cancel_scope.cancel)
            self._stack = stack.pop_all()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        stack, self._stack = self._stack, None
        if stack is not None:
            await stack.__aexit__(exc_type, exc, tb)

    @contextmanager
    def in_thread(self) -> Iterator[SweccisPeer]:
        """Serve from an event loop in a thread for the block (for sync tests)."""
        with start_blocking_portal() as portal, portal.wrap_async_context_manager(self):
            self._portal = portal
            try:
                yield self
            finally:
                self._portal = None

    def call(self, func: Callable[..., Awaitable[Any]], *args: Any) -> Any:
        """Run ``func(*args)`` on the peer's loop (from a sync test using ``in_thread``)."""
        assert self._portal is not None, "call() needs in_thread()"
        return self._portal.call(func, *args)

    # -- pushing ----------------------------------------------------------------------------------

    async def push_order(self, payload: bytes) -> int:
        """Send an order to every connection registered for Orders; how many got it."""
        doc_id = etree.fromstring(payload, _PARSER).get("id")
        assert doc_id is not None
        self.outbox[doc_id] = payload
        return await self.push_raw(payload)

    async def push_raw(self, payload: bytes, *, header: bytes | None = None) -> int:
        """Send ``payload`` as one frame (or after ``header`` instead of its own length) to
        every connection registered for Orders."""
        sent = 0
        for connection in list(self.connections):
            if "Orders" in connection.subscribe:
                with suppress(anyio.BrokenResourceError, anyio.ClosedResourceError, OSError):
                    if header is None:
                        await connection.send(payload)
                    else:
                        async with connection.lock:
                            await connection.stream.send(header + payload)
                    sent += 1
        return sent

    async def close_all(self) -> None:
        """Hang up on every client."""
        for connection in list(self.connections):
            await anyio.aclose_forcefully(connection.stream)

    # -- one connection -------------------------------------------------------------------------

    async def _serve(self, raw: anyio.abc.ByteStream, context: ssl.SSLContext) -> None:
        self.connection_count += 1
        try:
            if not self.is_down:
                await self._session(raw, context)
        finally:
            # Whatever ended it (a hang-up, a refused handshake, the peer stopping mid-way).
            await anyio.aclose_forcefully(raw)

    async def _session(self, raw: anyio.abc.ByteStream, context: ssl.SSLContext) -> None:
        try:
            stream = await AlertingTLSStream.wrap(
                raw, server_side=True, ssl_context=context, standard_compatible=False
            )
        except (ssl.SSLError, OSError, anyio.BrokenResourceError, anyio.EndOfStream) as exc:
            self.handshake_failures.append(str(getattr(exc, "reason", None) or exc))
            return
        connection = Connection(stream)
        self.connections.append(connection)
        reader = BufferedByteReceiveStream(stream)
        try:
            while True:
                (size,) = struct.unpack(">I", await reader.receive_exactly(4))
                if size > self.max_frame_bytes:
                    self.invalid.append((None, f"frame of {size} bytes"))
                    return
                if not await self._handle(connection, await reader.receive_exactly(size)):
                    return
        except (anyio.EndOfStream, anyio.IncompleteRead, anyio.BrokenResourceError):
            pass
        except (anyio.ClosedResourceError, ssl.SSLError, OSError):
            pass
        finally:
            self.connections.remove(connection)

    async def _handle(self, connection: Connection, payload: bytes) -> bool:
        """Answer one document; False when the connection is to close."""
        try:
            root = etree.fromstring(payload, _PARSER)
        except etree.XMLSyntaxError as exc:
            self.invalid.append((None, f"not XML: {exc}"))
            self.documents.append(Received("(garbage)", None, None))
            return True
        name = etree.QName(root).localname
        namespace = etree.QName(root).namespace or ""
        if namespace not in VERSION_OF:
            namespace = NAMESPACE  # checked against version 1, which refuses it
        doc_id = root.get("id") or root.get("ref")
        schema = self.schemas[namespace]
        if not schema.validate(root):
            problem = str(schema.error_log.last_error)
            self.invalid.append((doc_id, problem))
            self.documents.append(Received(name, doc_id, "rejected" if doc_id else None))
            if root.get("id"):
                await connection.send(
                    _ack(root.get("id", ""), "rejected", f"schema: {problem}", namespace)
                )
            return True
        if name == "Register":
            return await self._register(connection, root, namespace)
        if name == "Ack":
            ref, status = root.get("ref", ""), root.get("status", "")
            reason = root.findtext(f"{{{namespace}}}Reason")
            self.order_acks.append((ref, status, reason))
            self.outbox.pop(ref, None)
            self.documents.append(Received(name, ref, None))
            return True
        if name not in DATA_ROOTS:
            self.documents.append(Received(name, doc_id, None))
            return True
        assert doc_id is not None  # the schema requires it
        status, reason = self._verdict(connection, name, doc_id)
        if status == "accepted":
            self.accepted[doc_id] = root
        if status == "accepted" and self.drop_acks > 0:
            self.drop_acks -= 1
            self.documents.append(Received(name, doc_id, None))
            return True
        self.documents.append(Received(name, doc_id, status))
        if self.noise is not None:
            async with connection.lock:
                await connection.stream.send(self.noise)
        await connection.send(_ack(doc_id, status, reason, namespace))
        return True

    def _verdict(self, connection: Connection, name: str, doc_id: str) -> tuple[str, str | None]:
        if DATA_ROOTS[name] not in connection.publish:
            return "rejected", f"not registered to publish {DATA_ROOTS[name]}"
        if doc_id in self.reject:
            return "rejected", self.reject[doc_id]
        if doc_id in self.accepted:
            return "duplicate", None
        return "accepted", None

    async def _register(self, connection: Connection, root: etree._Element, namespace: str) -> bool:
        ns = f"{{{namespace}}}"
        publish = [e.text or "" for e in root.findall(f"{ns}Publish")]
        subscribe = [e.text or "" for e in root.findall(f"{ns}Subscribe")]
        self.registrations.append((root.findtext(f"{ns}Client") or "", publish, subscribe))
        self.documents.append(Received("Register", root.get("id"), None))
        if self.refuse_registration is not None:
            refused = _ack(root.get("id", ""), "rejected", self.refuse_registration, namespace)
            await connection.send(refused)
            return False
        connection.publish = set(publish) - self.withhold
        connection.subscribe = set(subscribe) - self.withhold
        answer = etree.Element(
            f"{ns}Registered",
            nsmap={None: namespace},
            version=VERSION_OF[namespace],
            ref=root.get("id", ""),
        )
        for tag, names in (("Publish", connection.publish), ("Subscribe", connection.subscribe)):
            for fas in sorted(names):
                etree.SubElement(answer, f"{ns}{tag}").text = fas
        await connection.send(bytes(etree.tostring(answer, encoding="UTF-8")))
        if "Orders" in connection.subscribe:
            for payload in list(self.outbox.values()):
                await connection.send(payload)
        return True
