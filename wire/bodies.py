"""One typed body per data-message kind, with the kind's name and plane (docs/architecture.md sec. 4).

Bodies are msgspec structs, encoded as msgpack maps in field order; a field whose default is
left out is not sent. Nested records (tracks, parts, arm states, commands) are typed dicts: the
domain code reads them as dicts, and msgspec checks their shape when a body is decoded. Bodies
that netsim carries to their destination inside a packet (``App``) name their kind in a
``type`` field, which decodes the packet's payload to the right struct.
"""

from __future__ import annotations

from typing import ClassVar, Literal, NotRequired, TypedDict

import msgspec

# Message kinds: the sensor plane (physics to camera, robot and abstract loops) ...
IMAGE = "image"
TRUTH = "truth"
JOINT_STATE = "joint_state"
JOINT_STATES = "joint_states"
# ... the actuation plane (robot and abstract loops to physics) ...
COMMANDS = "command"
# ... the radio plane: into netsim, and what netsim delivers (the packet's payload).
PACKET = "packet"
PACKETS = "packets"
QOS_CTL = "qos_ctl"
SLOT_TX = "slot_tx"
HELD = "held"
FRAME = "frame"
AFRAME = "aframe"
POSE = "pose"
QOS = "qos"
# ... and, on that plane, an Edge's counts of its frames shared by the two federates serving it.
EDGE_COUNTS = "edge_counts"

SENSE, ACT, NET = "sense", "act", "net"


class Part(TypedDict):
    """A part in play, as the physics knows it: cell frame, metres and metres per second."""

    task_id: int
    p: list[float]
    v: list[float]
    gripped: bool


class Track(TypedDict):
    """A tracked part as the Edge reports it: position (m), velocity (m/s), position sd (m; an
    ideal estimate has none)."""

    id: int
    t_us: int
    p: list[float]
    v: list[float]
    sd: NotRequired[float]


class ArmState(TypedDict):
    """An arm's measured joint positions (rad) and whether its cup holds a part."""

    q: list[float]
    gripped: bool


class Command(TypedDict):
    """An arm's joint position set-points (rad) and its suction, for one loop's arm."""

    loop: int
    q: list[float]
    suction: bool


class Body(msgspec.Struct, omit_defaults=True):
    """Base of every body: its kind and plane name it on the wire."""

    KIND: ClassVar[str]
    PLANE: ClassVar[str]


class Image(Body):
    """A rendered RGB-D capture of a detailed loop's camera; the pixels travel as the blob
    (``w`` x ``h`` RGB bytes, then as many little-endian uint16 depth values in mm)."""

    KIND: ClassVar[str] = IMAGE
    PLANE: ClassVar[str] = SENSE
    loop: int
    capture_us: int
    w: int
    h: int
    truth: list[Part]


class Truth(Body):
    """The parts an abstract loop's camera sees at ``capture_us`` (its frame is modelled)."""

    KIND: ClassVar[str] = TRUTH
    PLANE: ClassVar[str] = SENSE
    loop: int
    capture_us: int
    objects: list[Part]


class JointState(Body):
    """A detailed loop's arm state measured at ``t_us``."""

    KIND: ClassVar[str] = JOINT_STATE
    PLANE: ClassVar[str] = SENSE
    loop: int
    t_us: int
    q: list[float]
    gripped: bool


class JointStates(Body):
    """Every abstract loop's arm state measured at ``t_us``, by loop index (as text)."""

    KIND: ClassVar[str] = JOINT_STATES
    PLANE: ClassVar[str] = SENSE
    t_us: int
    states: dict[str, ArmState]


class Commands(Body):
    """Arm commands that take effect at the message's time."""

    KIND: ClassVar[str] = COMMANDS
    PLANE: ClassVar[str] = ACT
    commands: list[Command]


class App(Body, tag_field="type"):
    """A body netsim carries in a packet and delivers as a message of its own kind; the
    delivery adds the packet's id (or, for a modelled frame, the packets' ids and indices)."""

    PLANE: ClassVar[str] = NET


class Frame(App, tag=FRAME):
    """Packet ``idx`` of the ``n`` packets of a detailed loop's compressed frame (bytes: the blob);
    ``frame_id`` numbers the camera's captures, ``seq`` the frames it sent (a frame dropped for
    its PDP takes none), so that the Edge can count a frame sent and never received as lost."""

    KIND: ClassVar[str] = FRAME
    loop: int
    frame_id: int
    capture_us: int
    idx: int
    n: int
    seq: int
    packet_id: int | None = None


class Aframe(App, tag=AFRAME):
    """An abstract loop's frame of ``n`` packets; delivered: the indices and ids of the packets
    that arrived together. ``frame_id`` numbers the frames the camera sent (a frame dropped for
    its PDP takes none): it is the sent-frame sequence a detailed ``Frame`` carries as ``seq``."""

    KIND: ClassVar[str] = AFRAME
    loop: int
    frame_id: int
    n: int
    idx: list[int] | None = None
    packet_ids: list[int] | None = None


class Pose(App, tag=POSE):
    """The Edge's tracks for a loop's robot (``capture_us``: the frame they come from, when sent
    by a detailed Edge)."""

    KIND: ClassVar[str] = POSE
    loop: int
    tracks: list[Track]
    capture_us: int | None = None
    packet_id: int | None = None


class QosSignal(App, tag=QOS):
    """A loop's dynamic QoS for its camera: packet delivery probability and delay budget (None:
    none)."""

    KIND: ClassVar[str] = QOS
    loop: int
    pdp: float
    pdb_us: int | None
    packet_id: int | None = None


# What a packet carries to its destination.
Payload = Frame | Aframe | Pose | QosSignal


class Packet(Body, rename={"direction": "dir"}):
    """An IP packet of ``size`` bytes handed to the modem of ``ue`` (``direction`` ul or dl), for
    ``dst``; its flow's delay budget ``pdb_us`` (None: none)."""

    KIND: ClassVar[str] = PACKET
    PLANE: ClassVar[str] = NET
    ue: str
    direction: Literal["ul", "dl"]
    flow: str
    size: int
    dst: str
    pdb_us: int | None
    app: Payload


class Packets(Body, rename={"direction": "dir"}):
    """The packets (``sizes``, bytes) of one application message without payload bytes (an
    abstract loop's frame), entering together."""

    KIND: ClassVar[str] = PACKETS
    PLANE: ClassVar[str] = NET
    ue: str
    direction: Literal["ul", "dl"]
    flow: str
    sizes: list[int]
    dst: str
    pdb_us: int | None
    app: Payload


class QosCtl(Body):
    """A loop's QoS signalled to the gNB's scheduler (``policy.signalling: lower``)."""

    KIND: ClassVar[str] = QOS_CTL
    PLANE: ClassVar[str] = NET
    flow: str
    ue: str
    pdb_us: int | None
    pdp: float


class SlotTransmissions(Body):
    """The transmissions a netsim partition decided for slot ``slot`` (its index), per link, for
    the other partitions to decode theirs against (docs/architecture.md sec. 13): each (gNB
    index, the transmitting radio's hall index in UL or the receiving one's in DL, first PRB,
    PRBs, mean SNR per PRB before fading, dB)."""

    KIND: ClassVar[str] = SLOT_TX
    PLANE: ClassVar[str] = NET
    slot: int
    dl: list[tuple[int, int, int, int, float]]
    ul: list[tuple[int, int, int, int, float]]


class FadingProcesses(msgspec.Struct):
    """Fading processes of a hall's links handed from one netsim partition to another: per link
    its number, grid update and next innovation, then every link's gains (float32 per subband),
    diffuse states (complex64 per subband) and innovations left (float32), and its stream's
    position (the generator's state, JSON)."""

    links: list[int]
    updated: list[int]
    next: list[int]
    gain: bytes
    diffuse: bytes
    innovations: bytes
    streams: list[str]


class HeldPackets(Body):
    """What a netsim partition gives up when AGV ``ue``'s handover from one of its gNBs to
    another partition's starts at ``start_us`` (docs/architecture.md sec. 13): the packets its
    cell held for the AGV, each (packet id, flow, direction, IP bytes, enqueue time us), oldest
    first, which the target's partition forwards (or loses) with the others held when the
    handover ends; and the fading of the interference at the AGV, which its serving partition
    steps."""

    KIND: ClassVar[str] = HELD
    PLANE: ClassVar[str] = NET
    ue: str
    start_us: int
    packets: list[tuple[int, str, str, int, int]]
    fading: FadingProcesses


class EdgeCounts(Body):
    """One policy period of an Edge's frames as one of the two federates serving its loops saw
    them (docs/architecture.md sec. 7): the sum of their queueing delays (s), and how many
    completed, were counted lost and had stalled; the other folds them with its own."""

    KIND: ClassVar[str] = EDGE_COUNTS
    PLANE: ClassVar[str] = NET
    edge: str
    queued_s: float
    frames: int
    lost: int
    stalled: int
