"""Record one item's views with a LUCID Helios on a robot, in surffin's campaign layout.

An example for docs/acquisition.md: it needs LUCID's Arena SDK and its Python package
``arena_api`` (from LUCID's website; not on PyPI). surffin does not import it and the tests do
not run it. For each robot pose you give, it grabs one ``Coord3D_ABCY16`` frame and writes

- ``<folder>/<stem>.raw``: the buffer as the SDK delivers it (height x width x 4 uint16),
- ``<folder>/<stem>.pose.json``: the robot's flange pose, ``{"translation": [x, y, z] (mm),
  "quaternion": [w, x, y, z]}`` (campaign.yaml's ``camera.hand_eye`` turns it into the camera's),
- ``<folder>/<stem>.meta.json``: the acquisition settings (``camera.match_settings`` may name them),

and prints the ``camera.abcy16`` block (scale and offsets of the three axes) for campaign.yaml.
Moving the robot is yours: ``move_to`` below is a stub that must wait until the arm has stopped.

Usage: ``python acquire_helios.py FOLDER`` with the poses in ``POSES``.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
from arena_api.enums import PixelFormat
from arena_api.system import system

#: Robot flange poses (translation mm, quaternion w, x, y, z) at which to record, in order.
POSES = [
    ((0.0, 0.0, 450.0), (1.0, 0.0, 0.0, 0.0)),
    ((120.0, 0.0, 440.0), (0.9848, 0.0, 0.1736, 0.0)),
    ((-120.0, 0.0, 440.0), (0.9848, 0.0, -0.1736, 0.0)),
]
#: Settings kept fixed for the whole campaign (calibration included); recorded beside every view.
SETTINGS = {"Scan3dOperatingMode": "Distance1250mmSingleFreq", "ExposureTimeSelector": "Exp750Us"}


def move_to(translation, quaternion) -> None:
    """Move the robot and wait until it has settled (replace with your robot's interface)."""
    raise NotImplementedError("connect your robot here")


def configure(device) -> dict:
    """Set the pixel format and the fixed settings; return what a view's meta.json records."""
    nodemap = device.nodemap
    nodemap["PixelFormat"].value = PixelFormat.Coord3D_ABCY16
    for name, value in SETTINGS.items():
        nodemap[name].value = value
    stream = device.tl_stream_nodemap
    stream["StreamAutoNegotiatePacketSize"].value = True
    stream["StreamPacketResendEnable"].value = True
    return {name: nodemap[name].value for name in SETTINGS}


def abcy16_block(device) -> dict:
    """Scale and offset of each axis, mm, as campaign.yaml's ``camera.abcy16`` takes them."""
    nodemap = device.nodemap
    scales, offsets = [], []
    for axis in ("CoordinateA", "CoordinateB", "CoordinateC"):
        nodemap["Scan3dCoordinateSelector"].value = axis
        scales.append(float(nodemap["Scan3dCoordinateScale"].value))
        offsets.append(float(nodemap["Scan3dCoordinateOffset"].value))
    return {"signed": False, "scale": scales, "offset": offsets}


def grab(device) -> bytes:
    """One frame's raw ABCY16 bytes (height * width * 8)."""
    buffer = device.get_buffer()
    try:
        size = buffer.width * buffer.height * 4
        data = np.ctypeslib.as_array(buffer.pdata, shape=(size * 2,)).view(np.uint16).copy()
    finally:
        device.requeue_buffer(buffer)
    return data.tobytes()


def write_new(path: Path, content: bytes) -> None:
    """Write a file that must not exist yet: a campaign's raw data is never overwritten."""
    with open(path, "xb") as stream:
        stream.write(content)


def main(folder: Path) -> None:
    """Record one view per pose into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    device = system.create_device()[0]
    try:
        settings = configure(device)
        print("camera.abcy16:", json.dumps(abcy16_block(device)))
        with device.start_stream(1):
            for index, (translation, quaternion) in enumerate(POSES):
                move_to(translation, quaternion)
                time.sleep(0.5)  # let vibrations die out
                stem = f"v{index:02d}"
                write_new(folder / f"{stem}.raw", grab(device))
                pose = {"translation": list(translation), "quaternion": list(quaternion)}
                write_new(folder / f"{stem}.pose.json", json.dumps(pose).encode())
                meta = {**settings, "temperature_c": float(device.nodemap["DeviceTemperature"].value)}
                write_new(folder / f"{stem}.meta.json", json.dumps(meta).encode())
                print(f"{folder / stem}: recorded")
    finally:
        system.destroy_device()


if __name__ == "__main__":
    main(Path(sys.argv[1]))
