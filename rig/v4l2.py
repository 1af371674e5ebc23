"""The cameras ``--camera opencv:N`` drives: ``/dev/video*`` devices (V4L2: USB/UVC webcams, capture
cards) and what OpenCV reads of them, for ``lfrig camera list`` and ``lfrig camera info``.

Each device node is opened with ``cv2.VideoCapture`` and asked for its frame size, frame rate and
pixel format (FourCC), and one frame is read to check that it delivers. A node OpenCV cannot open
(V4L2 metadata nodes come in pairs with each UVC camera, a device another program holds) is listed
as such. The kernel's name of the device is read from ``/sys/class/video4linux/videoN/name``.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

DEV_DIR = Path("/dev")
SYSFS_DIR = Path("/sys/class/video4linux")


def video_devices(dev_dir: Path = DEV_DIR) -> list[Path]:
    """``dev_dir/video0``, ``video1``, ... in numeric order (no other names)."""
    found = [p for p in Path(dev_dir).glob("video*") if re.fullmatch(r"video\d+", p.name)]
    return sorted(found, key=lambda p: int(p.name[len("video"):]))


def fourcc_text(code: float) -> str | None:
    """OpenCV's ``CAP_PROP_FOURCC`` (a float holding four bytes) -> ``"MJPG"``; ``None`` when unset."""
    value = int(code)
    if value <= 0:
        return None
    text = "".join(chr((value >> (8 * i)) & 0xFF) for i in range(4))
    return text if text.isprintable() else f"0x{value:08x}"


def probe(source: int | str) -> dict[str, Any]:
    """What OpenCV reads of ``source`` (a device index or path): whether it opens, the backend, frame
    size (px), frame rate (Hz), FourCC, exposure and gain (backend units), and one frame's shape and dtype."""
    import cv2

    from rig.camera import quiet_opencv

    with quiet_opencv():
        cap = cv2.VideoCapture(source)
        try:
            if not cap.isOpened():
                return {"source": source, "opens": False}
            info: dict[str, Any] = {
                "source": source,
                "opens": True,
                "backend": cap.getBackendName(),
                "width_px": int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
                "height_px": int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
                "fps": round(float(cap.get(cv2.CAP_PROP_FPS)), 3),
                "fourcc": fourcc_text(cap.get(cv2.CAP_PROP_FOURCC)),
                "exposure": float(cap.get(cv2.CAP_PROP_EXPOSURE)),
                "gain": float(cap.get(cv2.CAP_PROP_GAIN)),
            }
            ok, frame = cap.read()
            info["frame"] = None if not ok or frame is None else {"shape": list(frame.shape), "dtype": str(frame.dtype)}
            return info
        finally:
            cap.release()


def sysfs_name(device: Path, sysfs_dir: Path = SYSFS_DIR) -> str | None:
    """The kernel's name of ``/dev/videoN`` (``/sys/class/video4linux/videoN/name``), if readable."""
    try:
        return (Path(sysfs_dir) / Path(device).name / "name").read_text(encoding="utf-8", errors="replace").strip() or None
    except OSError:
        return None


def list_opencv_devices(*, dev_dir: Path = DEV_DIR, sysfs_dir: Path = SYSFS_DIR) -> list[dict[str, Any]]:
    """Every ``/dev/video*`` node with its kernel name and :func:`probe`'s reading, the spec
    ``--camera`` takes (``opencv:/dev/videoN``) under ``"spec"``."""
    devices = []
    for path in video_devices(dev_dir):
        entry = {"spec": f"opencv:{path}", "path": str(path), "name": sysfs_name(path, sysfs_dir)}
        entry.update({k: v for k, v in probe(str(path)).items() if k != "source"})
        devices.append(entry)
    return devices


def describe_line(entry: dict[str, Any]) -> str:
    """One line of ``camera list`` for an entry of :func:`list_opencv_devices` or :func:`probe`."""
    head = entry.get("spec") or f"opencv:{entry['source']}"
    name = f"  {entry['name']}" if entry.get("name") else ""
    if not entry["opens"]:
        return f"{head}{name}  OpenCV cannot open it (a metadata node, or in use by another program)"
    frame = entry.get("frame")
    delivered = ("no frame read" if frame is None
                 else f"frame {' x '.join(str(n) for n in frame['shape'])} {frame['dtype']}")
    return (f"{head}{name}  {entry['width_px']} x {entry['height_px']} px, {entry['fps']:g} fps, "
            f"{entry['fourcc'] or 'format unknown'} ({entry['backend']}); {delivered}")
