"""The data-message bodies (``wire.bodies``): one struct per kind, encoded as the maps the trace
hash has always covered, decoded by kind, refused by name when malformed."""

from __future__ import annotations

import inspect

import msgpack
import msgspec
import pytest

from fabric import keys
from fabric.messages import BUNDLE, Bundle, Message, bundle_items, decode_data, encode_batch
from wire import bodies
from wire.bodies import App, Body, Frame, Packet, Packets, Pose, QosSignal

BODIES = [c for _, c in inspect.getmembers(bodies, inspect.isclass)
          if issubclass(c, Body) and c not in (Body, App)]


def test_every_body_names_one_kind_and_a_data_plane() -> None:
    kinds = [c.KIND for c in BODIES]
    assert len(kinds) == len(set(kinds)), f"two bodies share a kind: {sorted(kinds)}"
    assert BUNDLE not in kinds
    for cls in BODIES:
        assert cls.PLANE in keys.DATA_PLANES, cls
        if issubclass(cls, App):  # netsim delivers it under the kind its tag names
            assert cls.__struct_config__.tag == cls.KIND


def test_a_body_encodes_as_the_map_of_its_fields_in_order() -> None:
    # The trace hash covers every sent message's bytes: the struct must encode as the map it
    # stands for, fields in declaration order, a default-valued optional field left out.
    pose = Pose(loop=2, tracks=[{"id": 1, "t_us": 5, "p": [0.1, 0.0, 0.03], "v": [0.2, 0.0, 0.0], "sd": 0.004}])
    as_map = {"type": "pose", "loop": 2,
              "tracks": [{"id": 1, "t_us": 5, "p": [0.1, 0.0, 0.03], "v": [0.2, 0.0, 0.0], "sd": 0.004}]}
    assert msgspec.msgpack.encode(pose) == msgpack.packb(as_map, use_bin_type=True)
    qos = QosSignal(loop=0, pdp=0.5, pdb_us=None)  # a None without a default is sent
    assert msgspec.msgpack.decode(msgspec.msgpack.encode(qos)) == {"type": "qos", "loop": 0, "pdp": 0.5,
                                                                  "pdb_us": None}
    packet = Packet(ue="camera-0", direction="ul", flow="camera-0/video", size=1500, dst="edge", pdb_us=None,
                    app=Frame(loop=0, frame_id=1, capture_us=0, idx=0, n=3, seq=1))
    assert list(msgspec.msgpack.decode(msgspec.msgpack.encode(packet))) == [
        "ue", "dir", "flow", "size", "dst", "pdb_us", "app"]


def test_a_packet_carries_its_payload_back_as_the_right_struct() -> None:
    sent = Packets(ue="camera-3", direction="ul", flow="camera-3/video", sizes=[1500, 700], dst="loops",
                   pdb_us=80_000, app=bodies.Aframe(loop=3, frame_id=9, n=2))
    got = msgspec.msgpack.decode(msgspec.msgpack.encode(sent), type=Packets)
    assert got == sent and isinstance(got.app, bodies.Aframe)


def test_a_received_body_stays_undecoded_until_its_federate_decodes_it() -> None:
    msg = Message(2000, "netsim", "loops", 4, "net", Pose.KIND, Pose(loop=1, tracks=[]), None, 1)
    (back,) = decode_data(encode_batch([msg.encode()]))
    assert isinstance(back.body, msgspec.Raw)
    assert msgspec.msgpack.decode(back.body, type=Pose) == Pose(loop=1, tracks=[])


def test_a_bundle_gives_its_items_in_order_whether_in_memory_or_from_the_bus() -> None:
    items = [QosSignal(loop=0, pdp=1.0, pdb_us=None), Pose(loop=0, tracks=[])]
    bundle = Bundle([(b.KIND, b) for b in items])
    assert [k for k, _ in bundle_items(bundle)] == ["qos", "pose"]
    raw = Message(0, "netsim", "loops", 1, "net", BUNDLE, bundle).encode()
    (back,) = decode_data(raw)
    decoded = [(k, msgspec.msgpack.decode(b)) for k, b in bundle_items(back.body)]
    assert [k for k, _ in decoded] == ["qos", "pose"] and decoded[1][1]["type"] == "pose"


def test_a_malformed_body_is_refused_naming_the_field() -> None:
    raw = msgspec.msgpack.encode({"type": "qos", "loop": "zero", "pdp": 1.0, "pdb_us": None})
    with pytest.raises(msgspec.ValidationError, match=r"\$\.loop"):
        msgspec.msgpack.decode(raw, type=QosSignal)
