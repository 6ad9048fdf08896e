"""RGB-D frame compression: JPEG colour and decimated, losslessly coded 16-bit depth in one byte
string (the codecs and their measured sizes and costs: docs/perception.md)."""

from __future__ import annotations

import struct
import zlib
from typing import Literal

import cv2
import numpy as np

from domain.sensor import decimate_depth

DepthCodec = Literal["delta-zlib", "png"]
DEPTH_CODECS: tuple[DepthCodec, ...] = ("delta-zlib", "png")
_MAGIC = b"CF2"
# Magic ``CF2``, depth codec id (u8), decimation factor (u8), depth height and width (u16 each),
# then the lengths of the JPEG and depth parts (u32 each), big-endian; then both parts.
_HEADER = struct.Struct(">3sBBHHII")


def _zigzag(r: np.ndarray) -> np.ndarray:
    return ((r << 1) ^ (r >> 31)).astype(np.uint16)


def _unzigzag(u: np.ndarray) -> np.ndarray:
    u = u.astype(np.int32)
    return (u >> 1) ^ -(u & 1)


def encode_depth_delta_zlib(depth_mm: np.ndarray) -> bytes:
    """``depth_mm`` (uint16 HxW, mm) coded losslessly: 2-D difference, zigzag, byte planes, zlib
    level 1."""
    x = depth_mm.astype(np.int32)
    r = x.copy()
    r[:, 1:] -= x[:, :-1]
    r[1:, :] -= r[:-1, :].copy()
    # A difference of uint16 depths spans +-2^17: wrapped into int16 it keeps 16 bits, and the
    # decoder's sums, taken modulo 2^16 back in uint16, give every depth exactly (ranges beyond
    # 32.767 m, or jumps as large, included). Depths of a work cell never wrap.
    r = ((r + 32768) & 0xFFFF) - 32768
    u = _zigzag(r)
    planes = np.concatenate([(u >> 8).astype(np.uint8).ravel(), (u & 0xFF).astype(np.uint8).ravel()])
    return zlib.compress(planes.tobytes(), 1)


def decode_depth_delta_zlib(data: bytes, h: int, w: int) -> np.ndarray:
    """Inverse of ``encode_depth_delta_zlib``: the ``h`` x ``w`` depth (uint16, mm) that ``data``
    codes."""
    raw = np.frombuffer(zlib.decompress(data), np.uint8)
    if raw.size != 2 * h * w:
        raise ValueError("corrupt depth in frame (size mismatch)")
    u = (raw[: h * w].astype(np.uint16) << 8) | raw[h * w:]
    r = _unzigzag(u.reshape(h, w))
    return np.cumsum(np.cumsum(r, axis=0), axis=1).astype(np.uint16)


def encode_frame(rgb: np.ndarray, depth_mm: np.ndarray, jpeg_quality: int,
                 depth_codec: DepthCodec = "delta-zlib", decimation: int = 1) -> bytes:
    """Compress ``rgb`` (HxWx3 uint8) as JPEG of quality ``jpeg_quality`` (0-100) and
    ``depth_mm`` (HxW uint16, mm, 0 = invalid) with ``depth_codec``, after decimating it by
    ``decimation`` (lossy in resolution, lossless in value)."""
    ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    if not ok:
        raise RuntimeError("OpenCV failed to encode the colour image")
    dep = decimate_depth(depth_mm, decimation)
    if depth_codec == "delta-zlib":
        dbytes = encode_depth_delta_zlib(dep)
    elif depth_codec == "png":
        # PNG level 1: depth compresses little better at higher levels but costs much more CPU.
        ok, png = cv2.imencode(".png", dep, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:
            raise RuntimeError("OpenCV failed to encode the depth image")
        dbytes = png.tobytes()
    else:
        raise ValueError(f"unknown depth codec {depth_codec!r}; valid: {', '.join(DEPTH_CODECS)}")
    header = _HEADER.pack(_MAGIC, DEPTH_CODECS.index(depth_codec), decimation, dep.shape[0], dep.shape[1],
                          len(jpg), len(dbytes))
    return header + jpg.tobytes() + dbytes


def decode_frame(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of ``encode_frame`` for ``data``: (rgb uint8 HxWx3, depth uint16 HxW mm).
    Decimated depth is brought back to the colour resolution by repeating each block's value (0
    stays invalid)."""
    if len(data) < _HEADER.size:
        raise ValueError("not a compressed RGB-D frame (shorter than its header)")
    magic, codec, dec, dh, dw, n_jpg, n_dep = _HEADER.unpack_from(data)
    if magic != _MAGIC or _HEADER.size + n_jpg + n_dep != len(data) or codec >= len(DEPTH_CODECS) or dec < 1:
        raise ValueError("not a compressed RGB-D frame (bad header or truncated)")
    jpg = np.frombuffer(data, np.uint8, n_jpg, _HEADER.size)
    bgr = cv2.imdecode(jpg, cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError("corrupt JPEG in frame")
    dbytes = data[_HEADER.size + n_jpg:]
    if DEPTH_CODECS[codec] == "delta-zlib":
        try:
            depth = decode_depth_delta_zlib(dbytes, dh, dw)
        except zlib.error as exc:
            raise ValueError(f"corrupt depth in frame ({exc})") from None
    else:
        png = cv2.imdecode(np.frombuffer(dbytes, np.uint8), cv2.IMREAD_UNCHANGED)
        if png is None or png.shape != (dh, dw):
            raise ValueError("corrupt PNG depth in frame")
        depth = png
    h, w = bgr.shape[:2]
    if dec > 1:
        full = np.zeros((h, w), np.uint16)
        up = np.repeat(np.repeat(depth, dec, axis=0), dec, axis=1)
        full[: up.shape[0], : up.shape[1]] = up[:h, :w]
        depth = full
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), depth


def split_packets(payload_bytes: int, mtu_bytes: int) -> list[int]:
    """IP packet sizes (bytes) carrying ``payload_bytes`` of application data in packets of at
    most ``mtu_bytes`` (IPv4 + UDP + 12-byte application header per packet)."""
    overhead = 20 + 8 + 12
    room = mtu_bytes - overhead
    n = max(1, -(-payload_bytes // room))
    sizes = [room + overhead] * (n - 1)
    sizes.append(payload_bytes - room * (n - 1) + overhead)
    return sizes


def slot_after(t_us: int, slot_us: int) -> int:
    """The first boundary of ``slot_us`` (us) slots strictly after ``t_us`` (us): when a packet
    handed to the modem at ``t_us`` enters the UE buffer."""
    return (t_us // slot_us + 1) * slot_us
