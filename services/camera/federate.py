"""The camera node: receives rendered RGB-D frames, applies the D435-class sensor model
(domain/sensor.py), keeps each with probability PDP_r (the Edge's
co-design signal), compresses kept frames on its throttled CPU and hands them to the modem as
IP packets of an uplink flow to the Edge.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from domain.codec import encode_frame, slot_after, split_packets
from domain.frame_keep import FrameKeep
from domain.partitions import load_route
from domain.sensor import sense, sensor_for
from fabric.compute import ComputeNode
from fabric.federate import Federate, Handlers
from fabric.messages import Message
from wire.bodies import Frame, Image, Packet, QosSignal


class CameraFederate(Federate):
    role = "camera"

    def setup(self) -> None:
        self.loop = int(self.name.rsplit("-", 1)[1])
        self.cpu = ComputeNode(self.name, self.scenario.nodes.camera, self.rng("compute"))
        self.record_jobs(self.cpu)
        self.netsim = load_route(self.scenario, self.results_dir).netsim_of(self.name)
        self.frames = self.table("frames")
        self.frames_kept = 0
        self.bytes_kept = 0
        self.keeper = FrameKeep(self.scenario.camera.frame_keep, self.rng("pdp"))
        self.pdp = 1.0
        self.pdb_us: int | None = None
        self.frame_id = 0  # captures
        self.sent = 0  # frames sent: the sequence the Edge counts its lost frames by
        self.sensor = sensor_for(self.scenario.camera)
        self.sensor_rng = self.rng("sensor")
        cv2.setNumThreads(self.cpu.threads)  # OpenCV at the node's cores: one where cpus <= 1

    def handlers(self) -> Handlers:
        return {Image: self._on_image, QosSignal: self._on_qos}

    def _on_qos(self, qos: QosSignal, msg: Message) -> None:
        self.pdp = float(qos.pdp)
        self.pdb_us = qos.pdb_us

    def _on_image(self, image: Image, msg: Message) -> None:
        sc = self.scenario
        fid = self.frame_id
        self.frame_id += 1
        keep = self.keeper.keep(self.pdp)
        row: dict[str, Any] = {"loop": self.loop, "frame_id": fid, "capture_us": image.capture_us,
                               "pdp": self.pdp, "kept": keep, "bytes": 0, "packets": 0, "ready_us": None}
        if not keep:
            self.frames.append(row)
            return
        w, h = image.w, image.h
        blob = msg.blob or b""
        rgb = np.frombuffer(blob, np.uint8, w * h * 3).reshape(h, w, 3)
        depth = np.frombuffer(blob, np.uint16, w * h, w * h * 3).reshape(h, w)
        # The sensor's noise and invalid pixels happen in the camera hardware, not on the node's CPU.
        rgb, depth = sense(self.sensor, rgb, depth, self.sensor_rng)
        cam = sc.camera
        data, ready = self.cpu.run("compress", self.now, encode_frame, rgb, depth, cam.jpeg_quality,
                                   cam.depth_codec, cam.depth_decimation)
        # The packet count follows from the size alone: the row is complete now.
        row.update(bytes=len(data), ready_us=ready, packets=len(split_packets(len(data), cam.mtu_bytes)))
        self.frames.append(row)
        self.frames_kept += 1
        self.bytes_kept += len(data)
        self.schedule(ready, self._transmit, fid, self.sent, image.capture_us, data)
        self.sent += 1

    def _transmit(self, fid: int, seq: int, capture_us: int, data: bytes) -> None:
        sc = self.scenario
        sizes = split_packets(len(data), sc.camera.mtu_bytes)
        enter = slot_after(self.now, sc.netsim.slot_us)
        offset = 0
        for idx, size in enumerate(sizes):
            chunk = data[offset:offset + size - 40]
            offset += len(chunk)
            self.send(self.netsim, enter, Packet(
                ue=self.name, direction="ul", flow=f"{self.name}/video", size=size, dst="edge",
                pdb_us=self.pdb_us,
                app=Frame(loop=self.loop, frame_id=fid, capture_us=capture_us, idx=idx, n=len(sizes),
                          seq=seq),
            ), chunk)

    def finish(self, reason: str) -> dict[str, Any]:
        kept = self.frames_kept
        return {"frames": self.frame_id, "frames_kept": kept,
                "bytes_per_frame": self.bytes_kept / kept if kept else 0.0,
                "compute_speed": self.cpu.speed_summary(self.now)}
