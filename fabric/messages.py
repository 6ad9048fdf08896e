"""Message schemas: the data envelope every federate exchanges and the control records.

Data messages are a compact msgpack array whose body is a typed struct (``wire``: fabric knows
no body, only that it has a ``KIND`` and a ``PLANE``; a received body stays undecoded until its
federate decodes it by kind); bulk payloads such as frames travel as raw bytes in ``blob``.
Control messages are schema-versioned pydantic records serialised as msgpack. Every message
carries its delivery time (integer microseconds), its source and a per-source sequence number,
which together give the processing order (t_us, src, seq).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Protocol

import msgpack
import msgspec
from pydantic import BaseModel, ConfigDict, Field

SCHEMA_VERSION = 1


class MessageError(ValueError):
    """A message that cannot be decoded or does not match its schema."""


class Body(Protocol):
    """What fabric needs of a data message's body: its kind and plane (``wire.bodies``)."""

    KIND: ClassVar[str]
    PLANE: ClassVar[str]


@dataclass(slots=True)
class Message:
    """A data message between federates, delivered at ``t_us``. ``body``: the sender's struct,
    or, received from the bus, its undecoded bytes (``msgspec.Raw``)."""

    t_us: int
    src: str
    dst: str
    seq: int
    plane: str
    kind: str
    body: Any
    blob: bytes | None = None
    window: int = 0  # window in which it was sent: the barrier counts per sending window

    def encode(self) -> bytes:
        return _encode([SCHEMA_VERSION, self.t_us, self.src, self.dst, self.seq, self.plane, self.kind,
                        self.body, self.blob, self.window])

    @classmethod
    def decode(cls, raw: bytes) -> Message:
        try:
            v, t_us, src, dst, seq, plane, kind, body, blob, window = _decode_envelope(raw)
        except (msgspec.DecodeError, msgspec.ValidationError) as exc:  # malformed bytes from the wire
            raise MessageError(f"undecodable data message: {exc}") from exc
        if v != SCHEMA_VERSION:
            raise MessageError(f"data message schema v{v}, this build speaks v{SCHEMA_VERSION}")
        return cls(t_us, src, dst, seq, plane, kind, body, blob, window)


_Envelope = tuple[int, int, str, str, int, str, str, msgspec.Raw, bytes | None, int]
_encode = msgspec.msgpack.Encoder().encode
_decode_envelope = msgspec.msgpack.Decoder(_Envelope).decode

# The kind of a data message that carries several messages for one destination and delivery
# time (``Federate.send_bundle``), each as [kind, body], no blob.
BUNDLE = "bundle"


class Bundle(msgspec.Struct):
    """The body of a bundle: its messages' kinds and bodies, in sending order."""

    KIND: ClassVar[str] = BUNDLE
    items: list[tuple[str, Any]]


class _RawBundle(msgspec.Struct):
    items: list[tuple[str, msgspec.Raw]]


_decode_raw_bundle = msgspec.msgpack.Decoder(_RawBundle).decode


def bundle_items(body: Any) -> list[tuple[str, Any]]:
    """The [kind, body] items of a bundle's body (sent in memory, or undecoded from the bus)."""
    if isinstance(body, Bundle):
        return body.items
    try:
        return list(_decode_raw_bundle(body).items)
    except (msgspec.DecodeError, msgspec.ValidationError, TypeError) as exc:
        raise MessageError(f"malformed bundle: {exc}") from exc


# A batch: every data message one federate sent to one destination's inbox key in one window,
# in sending order, as one bus message (the per-message cost of the bus is paid once a window).
_BATCH = "batch"
_decode_batch = msgspec.msgpack.Decoder(tuple[str, list[bytes]]).decode
_BATCH_HEAD = 0x92  # a two-element msgpack array; a single message's envelope has ten


def encode_batch(raws: list[bytes]) -> bytes:
    """One bus payload for several encoded data messages (a single message goes as it is)."""
    if len(raws) == 1:
        return raws[0]
    return _encode([_BATCH, raws])


def decode_data(payload: bytes) -> list[Message]:
    """The data messages of one bus payload: a single message or a batch."""
    if payload[:1] != bytes((_BATCH_HEAD,)):
        return [Message.decode(payload)]  # a single message, decoded once (a frame's blob is large)
    try:
        tag, raws = _decode_batch(payload)
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise MessageError(f"undecodable data message: {exc}") from exc
    if tag != _BATCH:
        raise MessageError(f"undecodable data message: a batch tagged {tag!r}")
    return [Message.decode(raw) for raw in raws]


class ControlRecord(BaseModel):
    """Base of control-plane records: versioned, strict, msgpack on the wire."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    v: int = Field(default=SCHEMA_VERSION, description="schema version")
    KIND: ClassVar[str] = "control"

    def encode(self) -> bytes:
        return msgpack.packb(self.model_dump(), use_bin_type=True)

    @classmethod
    def decode(cls, raw: bytes) -> Any:
        try:
            data = msgpack.unpackb(raw, raw=False)
        except Exception as exc:
            raise MessageError(f"undecodable {cls.KIND} record: {exc}") from exc
        if not isinstance(data, dict) or data.get("v") != SCHEMA_VERSION:
            raise MessageError(f"{cls.KIND} record has schema {data!r:.80}, expected v{SCHEMA_VERSION}")
        return cls.model_validate(data)


class Ready(ControlRecord):
    KIND: ClassVar[str] = "ready"
    federate: str = Field(description="name of the federate that is ready")
    pid: int = Field(description="OS process id, for diagnostics")


class Advance(ControlRecord):
    KIND: ClassVar[str] = "advance"
    window: int = Field(description="window index, from 0")
    t_start_us: int = Field(description="start of the window (inclusive), microseconds")
    t_end_us: int = Field(description="end of the window (exclusive), microseconds")
    expected_in: dict[str, int] = Field(
        description="per federate: number of data messages sent to it in all earlier windows; it "
        "waits until it has received that many (counted by sending window) before processing"
    )
    federates: list[str] | None = Field(
        default=None, description="the federates that take part in this window (None: all); the "
        "others have no event in it and nothing new sent to them, and neither process nor reply"
    )


class Done(ControlRecord):
    KIND: ClassVar[str] = "done"
    federate: str = Field(description="reporting federate")
    window: int = Field(description="window index this report closes")
    t_end_us: int = Field(description="end of the window processed")
    sent_to: dict[str, int] = Field(description="cumulative data messages sent, per destination")
    next_event_us: int | None = Field(description="earliest pending internal event or input")
    earliest_sent_us: int | None = Field(description="earliest delivery time sent in this window")
    horizon_us: int | None = Field(
        default=None, description="no message to another participant will be sent before this time "
        "unless one arrives from another participant first (None: no such promise); a participant "
        "alone with something to do may be given a window up to the end of the base window that "
        "holds it (what it sends then arrives no earlier)")
    error: str | None = Field(default=None, description="set when the federate failed")


class Stop(ControlRecord):
    KIND: ClassVar[str] = "stop"
    reason: str = Field(description="why the run stops: completed, failed, cancelled, timed_out")
    t_us: int = Field(description="simulated time at which the run stopped")


class Stopped(ControlRecord):
    KIND: ClassVar[str] = "stopped"
    federate: str = Field(description="federate that has written its results and is leaving")
    trace_hash: str = Field(description="sha256 over every event the federate processed and sent")
    events: int = Field(description="number of events processed")
    summary: dict[str, Any] = Field(default_factory=dict, description="federate KPIs")
