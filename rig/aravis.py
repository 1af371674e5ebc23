"""A GenICam machine-vision camera through Aravis (implements :class:`rig.protocols.Camera`).

Aravis is the open GenICam stack on Linux (GigE Vision and USB3 Vision); Python reaches it through
PyGObject (``gi.require_version("Aravis", "0.8")``). ``./setup.sh`` installs both. Aravis ships an
in-process simulated camera, ``Fake_1`` (interface ``Fake``, enabled here for any device id starting
with ``Fake``): the test suite runs against it.

Fresh frames
------------
Acquisition runs continuously from :meth:`AravisCamera.__init__` to :meth:`~AravisCamera.close`.
:meth:`~AravisCamera.trigger` first returns every frame already delivered to the stream's queue to the
pool (unseen), records the host time ``t0``, fires the trigger, and then returns the first complete
frame whose host receive time (``ArvBuffer`` system timestamp) is no earlier than ``t0``: a triggered
camera sends a frame only for a trigger, so that frame is the one this trigger exposed. In
free-running mode (``trigger="free"``) the camera streams on its own, and the bound is
``t0 + exposure + one frame period`` (a frame's readout is shorter than its period): the earliest a
frame whose exposure began after ``t0`` can arrive. So a frame exposed while the stage was still
moving is never returned.

Triggers
--------
``"software"``
    ``TriggerMode=On``, ``TriggerSource=Software`` for ``FrameStart``; each view executes
    ``TriggerSoftware``.
a line name (``"Line1"``...)
    Hardware trigger: ``TriggerSource`` set to that line, rising edge. With ``hardware_trigger=`` a
    callable switching an output wired to the line (e.g. :meth:`rig.grbl.GrblStage.set_output`, the
    stage's ``M8``), each view pulses it; without one, an outside device fires the line.
``"free"``
    ``TriggerMode=Off``: the camera streams at its frame rate; stale frames are dropped as above.

Pixel formats
-------------
``Mono8`` -> ``(H, W) uint8``; ``Mono10/12/14/16`` and the packed ``Mono10p``, ``Mono12p``,
``Mono12Packed`` -> ``(H, W) uint16`` with the significant bits moved to the top (a 12-bit value ``v``
is stored as ``v << 4``, so the full range of the file is used; the shift is in the journal);
``Bayer{RG,GR,GB,BG}{8,10,12,16}`` -> demosaiced ``(H, W, 3)`` RGB (``uint8`` or ``uint16``);
``RGB8``/``BGR8`` -> ``(H, W, 3) uint8`` RGB. :func:`decode_frame` is the pure conversion.

Units: exposure in microseconds (SFNC ``ExposureTime``/``ExposureTimeAbs``); gain in dB when the
camera has the SFNC ``Gain`` feature, else the camera's raw ``GainRaw`` steps (``gain_unit`` in the
settings says which). Every setting is read back from the device for every frame
(:meth:`AravisCamera.settings`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from rig.camera import CameraError
from rig.clock import Clock, SystemClock

log = logging.getLogger(__name__)

SETUP_HINT = (
    "run ./setup.sh (it installs gir1.2-aravis-0.8, libaravis-0.8-0 and PyGObject), "
    "or by hand: sudo apt-get install gir1.2-aravis-0.8 and uv sync --extra aravis"
)


class CameraTimeoutError(CameraError):
    """The camera delivered no (fresh, complete) frame within the timeout."""


# --------------------------------------------------------------------------------------------------
# Pixel formats (pure)


@dataclass(frozen=True)
class PixelFormat:
    """How to turn a buffer of one GenICam pixel format into an array."""

    name: str
    kind: str  # "mono", "bayer", "rgb", "bgr"
    bits: int  # significant bits per sample
    packing: str = "plain"  # "plain" (8 or 16-bit little-endian containers), "p" (PFNC LSB-packed), "gvpacked"
    pattern: str | None = None  # Bayer: colours of the top-left 2x2 block, row by row ("RG": R G / G B)


def _pixel_formats() -> dict[str, PixelFormat]:
    formats: dict[str, PixelFormat] = {"Mono8": PixelFormat("Mono8", "mono", 8)}
    for bits in (10, 12, 14, 16):
        formats[f"Mono{bits}"] = PixelFormat(f"Mono{bits}", "mono", bits)
    formats["Mono10p"] = PixelFormat("Mono10p", "mono", 10, "p")
    formats["Mono12p"] = PixelFormat("Mono12p", "mono", 12, "p")
    formats["Mono12Packed"] = PixelFormat("Mono12Packed", "mono", 12, "gvpacked")
    for pattern in ("RG", "GR", "GB", "BG"):
        for bits in (8, 10, 12, 16):
            name = f"Bayer{pattern}{bits}"
            formats[name] = PixelFormat(name, "bayer", bits, pattern=pattern)
    formats["RGB8"] = PixelFormat("RGB8", "rgb", 8)
    formats["BGR8"] = PixelFormat("BGR8", "bgr", 8)
    return formats


#: The pixel formats :func:`decode_frame` understands, by GenICam (PFNC) name.
PIXEL_FORMATS = _pixel_formats()

# GenICam names a Bayer pattern by its top-left 2x2 block; OpenCV by the second row's second and
# third pixels. RG (R G / G B) is OpenCV's "BG", and so on (checked in tests/test_rig_aravis.py).
_OPENCV_BAYER = {"RG": "BG", "GR": "GB", "GB": "GR", "BG": "RG"}


def unpack_12p(data: np.ndarray, count: int) -> np.ndarray:
    """PFNC ``Mono12p``: two 12-bit pixels in three bytes, LSB first. Returns ``count`` values (uint16)."""
    b = data[: (count + 1) // 2 * 3].astype(np.uint16).reshape(-1, 3)
    out = np.empty((b.shape[0], 2), np.uint16)
    out[:, 0] = b[:, 0] | ((b[:, 1] & 0x0F) << 8)
    out[:, 1] = (b[:, 1] >> 4) | (b[:, 2] << 4)
    return out.reshape(-1)[:count]


def unpack_12_gvpacked(data: np.ndarray, count: int) -> np.ndarray:
    """GigE Vision ``Mono12Packed``: byte 0 = p0 bits 11..4, byte 1 = p1 bits 3..0 << 4 | p0 bits 3..0,
    byte 2 = p1 bits 11..4. Returns ``count`` values (uint16)."""
    b = data[: (count + 1) // 2 * 3].astype(np.uint16).reshape(-1, 3)
    out = np.empty((b.shape[0], 2), np.uint16)
    out[:, 0] = (b[:, 0] << 4) | (b[:, 1] & 0x0F)
    out[:, 1] = (b[:, 2] << 4) | (b[:, 1] >> 4)
    return out.reshape(-1)[:count]


def unpack_10p(data: np.ndarray, count: int) -> np.ndarray:
    """PFNC ``Mono10p``: four 10-bit pixels in five bytes, LSB first. Returns ``count`` values (uint16)."""
    b = data[: (count + 3) // 4 * 5].astype(np.uint16).reshape(-1, 5)
    out = np.empty((b.shape[0], 4), np.uint16)
    out[:, 0] = b[:, 0] | ((b[:, 1] & 0x03) << 8)
    out[:, 1] = (b[:, 1] >> 2) | ((b[:, 2] & 0x0F) << 6)
    out[:, 2] = (b[:, 2] >> 4) | ((b[:, 3] & 0x3F) << 4)
    out[:, 3] = (b[:, 3] >> 6) | (b[:, 4] << 2)
    return out.reshape(-1)[:count]


def packed_size(fmt: PixelFormat, width: int, height: int) -> int:
    """Bytes of one ``width x height`` frame in ``fmt``."""
    count = width * height
    channels = 3 if fmt.kind in ("rgb", "bgr") else 1
    if fmt.packing == "p" and fmt.bits == 10:
        return (count + 3) // 4 * 5
    if fmt.packing in ("p", "gvpacked"):
        return (count + 1) // 2 * 3
    return count * channels * (1 if fmt.bits == 8 else 2)


def decode_frame(data: bytes | np.ndarray, *, pixel_format: str, width: int, height: int) -> np.ndarray:
    """Turn one frame's bytes into an image array.

    Parameters
    ----------
    data
        The frame as the camera sent it (at least :func:`packed_size` bytes; extra bytes are ignored).
    pixel_format
        GenICam (PFNC) name, one of :data:`PIXEL_FORMATS`.
    width, height
        Frame size in pixels.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` for mono, ``(H, W, 3)`` RGB for Bayer and RGB/BGR formats; ``uint8`` for 8-bit
        formats, else ``uint16`` with the ``bits`` significant bits shifted to the top (``v << (16 - bits)``).

    Raises
    ------
    CameraError
        Unknown pixel format, or fewer bytes than such a frame needs.
    """
    fmt = PIXEL_FORMATS.get(pixel_format)
    if fmt is None:
        raise CameraError(
            f"pixel format {pixel_format!r} is not supported; choose one of {', '.join(PIXEL_FORMATS)} "
            "(lfrig camera info SPEC lists what the camera offers)"
        )
    raw = np.frombuffer(data, np.uint8) if not isinstance(data, np.ndarray) else data.reshape(-1).view(np.uint8)
    need = packed_size(fmt, width, height)
    if raw.size < need:
        raise CameraError(
            f"a {pixel_format} frame of {width}x{height} needs {need} bytes, the camera sent {raw.size}; "
            "the frame is truncated (check the network packet size or USB bandwidth)"
        )
    count = width * height
    if fmt.packing == "p":
        values = unpack_12p(raw, count) if fmt.bits == 12 else unpack_10p(raw, count)
    elif fmt.packing == "gvpacked":
        values = unpack_12_gvpacked(raw, count)
    elif fmt.bits == 8:
        channels = 3 if fmt.kind in ("rgb", "bgr") else 1
        values = raw[: count * channels].copy()
    else:
        values = raw[: count * 2].view("<u2").astype(np.uint16)
    if fmt.bits not in (8, 16):
        values = values << np.uint16(16 - fmt.bits)
    if fmt.kind == "mono":
        return values.reshape(height, width)
    if fmt.kind in ("rgb", "bgr"):
        image = values.reshape(height, width, 3)
        return np.ascontiguousarray(image[:, :, ::-1] if fmt.kind == "bgr" else image)
    import cv2

    code = getattr(cv2, f"COLOR_Bayer{_OPENCV_BAYER[fmt.pattern]}2RGB")  # type: ignore[index]
    return cv2.cvtColor(values.reshape(height, width), code)


# --------------------------------------------------------------------------------------------------
# Aravis access


def load_aravis() -> Any:
    """The ``Aravis`` GObject-introspection module, or a :class:`CameraError` saying how to install it."""
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis  # type: ignore[attr-defined]
    except (ImportError, ValueError) as error:
        raise CameraError(f"the Aravis camera driver is not installed ({error}); {SETUP_HINT}") from None
    return Aravis


def _is_fake(device_id: str | None) -> bool:
    return bool(device_id) and device_id.startswith("Fake")  # type: ignore[union-attr]


def _gerror_message(error: Exception) -> str:
    return getattr(error, "message", None) or str(error)


def _glib_error() -> type[BaseException]:
    from gi.repository import GLib  # type: ignore[attr-defined]

    return GLib.GError


def list_devices(*, include_fake: bool = False) -> list[dict[str, Any]]:
    """The GenICam cameras Aravis finds (GigE Vision on every network interface, USB3 Vision).

    With ``include_fake``, Aravis's simulated camera ``Fake_1`` is listed too.
    """
    aravis = load_aravis()
    if include_fake:
        aravis.enable_interface("Fake")
    aravis.update_device_list()
    devices = []
    for i in range(aravis.get_n_devices()):
        devices.append({
            "id": aravis.get_device_id(i),
            "vendor": aravis.get_device_vendor(i),
            "model": aravis.get_device_model(i),
            "serial": aravis.get_device_serial_nbr(i),
            "protocol": aravis.get_device_protocol(i),
            "address": aravis.get_device_address(i),
            "physical_id": aravis.get_device_physical_id(i),
        })
    return devices


def parse_spec(spec: str) -> str | None:
    """``"aravis:"`` -> ``None`` (the first device); ``"aravis:Basler-1234"`` -> ``"Basler-1234"``."""
    if not spec.startswith("aravis:"):
        raise CameraError(f"camera spec {spec!r}: expected aravis: or aravis:DEVICE_ID (lfrig camera list shows the ids)")
    device_id = spec[len("aravis:"):].strip()
    return device_id or None


def parse_trigger(text: str) -> str:
    """``software``, ``free`` or a line name (``Line1``, ``Line0``...), as given."""
    text = text.strip()
    if text.lower() in ("software", "free"):
        return text.lower()
    if not text or not text.replace("_", "").isalnum():
        raise CameraError(f"trigger {text!r}: give software, free, or the camera's trigger line (e.g. Line1)")
    return text


class AravisCamera:
    """A GenICam camera opened through Aravis; a context manager.

    Parameters
    ----------
    device_id
        Aravis device id (``lfrig camera list``), an IP address for GigE Vision, or ``None`` for the
        first device found. Ids starting with ``Fake`` open Aravis's simulated camera.
    pixel_format
        GenICam pixel format to set (e.g. ``"Mono12"``, ``"BayerRG8"``); ``None`` keeps the camera's.
    roi
        ``(x, y, width, height)`` in pixels of the (binned) sensor; ``None`` keeps the camera's region.
    binning
        ``(horizontal, vertical)`` or one number for both; ``None`` keeps the camera's.
    exposure_us
        Exposure time in microseconds (auto exposure is switched off); ``None`` keeps the camera's.
    gain_db
        Gain in dB (auto gain is switched off; a camera without the SFNC ``Gain`` feature takes its raw
        ``GainRaw`` steps instead, and ``gain_unit`` says so); ``None`` keeps the camera's.
    trigger
        ``"software"`` (default), ``"free"``, or a trigger line name for a hardware trigger; see the
        module docstring.
    hardware_trigger
        ``callable(on: bool)`` switching an output wired to the trigger line (with a line trigger).
    trigger_pulse_s
        How long the output stays on.
    timeout_s
        Longest wait for a fresh frame after the trigger (beyond the exposure time).
    buffers
        Frame buffers queued on the stream.
    clock
        Only for the trigger pulse's sleep (the stage's clock); frame timeouts use the host clock, as
        the camera does.
    acquire
        ``False`` opens the camera without changing any setting or starting acquisition (to describe
        it); :meth:`trigger` then fails.

    Raises
    ------
    CameraError
        The device cannot be opened, a value is outside the camera's range, or the pixel format is one
        lfrig cannot decode. The message names the value and what the camera accepts.
    """

    def __init__(
        self,
        device_id: str | None = None,
        *,
        pixel_format: str | None = None,
        roi: tuple[int, int, int, int] | None = None,
        binning: int | tuple[int, int] | None = None,
        exposure_us: float | None = None,
        gain_db: float | None = None,
        trigger: str = "software",
        hardware_trigger: Callable[[bool], None] | None = None,
        trigger_pulse_s: float = 0.01,
        timeout_s: float = 5.0,
        buffers: int = 4,
        clock: Clock | None = None,
        acquire: bool = True,
    ) -> None:
        if timeout_s <= 0:
            raise CameraError(f"frame timeout must be > 0 s; got {timeout_s}")
        if buffers < 1:
            raise CameraError(f"buffers must be >= 1; got {buffers}")
        self._aravis = load_aravis()
        self._gerror = _glib_error()
        self.trigger_mode = parse_trigger(trigger)
        if hardware_trigger is not None and self.trigger_mode in ("software", "free"):
            raise CameraError(
                f"a hardware trigger output needs a trigger line (e.g. trigger='Line1'), not trigger={self.trigger_mode!r}"
            )
        self.hardware_trigger = hardware_trigger
        self.trigger_pulse_s = float(trigger_pulse_s)
        self.timeout_s = float(timeout_s)
        self._buffers = int(buffers)
        self.clock = clock if clock is not None else SystemClock()
        if isinstance(binning, int):
            binning = (binning, binning)
        self.requested: dict[str, Any] = {
            "pixel_format": pixel_format, "roi": list(roi) if roi is not None else None,
            "binning": list(binning) if binning is not None else None,
            "exposure_us": exposure_us, "gain_db": gain_db, "trigger": self.trigger_mode,
        }
        self.name = device_id or "(first device)"
        if _is_fake(device_id):
            self._aravis.enable_interface("Fake")
        try:
            self._cam = self._aravis.Camera.new(device_id)
        except self._gerror as error:
            raise CameraError(
                f"cannot open Aravis camera {self.name}: {_gerror_message(error)}; "
                "`lfrig camera list` shows the cameras found (check power, cable, network address and "
                "that no other program holds the camera)"
            ) from None
        if self._cam is None:
            raise CameraError(f"no Aravis camera found ({self.name}); `lfrig camera list` shows what is connected")
        if device_id is None:  # Camera.new(None) opened the first device of Aravis's list
            self.name = self._aravis.get_device_id(0) if self._aravis.get_n_devices() else self.name
        self._stream: Any = None
        self._acquiring = False
        self._frames = 0
        self._last: dict[str, Any] = {}
        self._stale_dropped = 0
        self._failed_buffers = 0
        if not acquire:  # only to describe the camera: change nothing on it
            return
        try:
            self._configure(pixel_format=pixel_format, roi=roi, binning=binning, exposure_us=exposure_us, gain_db=gain_db)
            self._start()
        except BaseException:
            self.close()
            raise

    # ---- configuration -------------------------------------------------------------------------

    def _call(self, what: str, function: Callable[..., Any], *args: Any) -> Any:
        try:
            return function(*args)
        except self._gerror as error:
            raise CameraError(f"camera {self.name}: {what} failed: {_gerror_message(error)}") from None

    def _check_range(self, what: str, value: float, bounds: Any, unit: str) -> None:
        lo, hi = float(bounds.min), float(bounds.max)
        if not lo <= value <= hi:
            raise CameraError(f"camera {self.name}: {what} {value:g} {unit} is outside its range [{lo:g}, {hi:g}] {unit}")

    def _configure(self, *, pixel_format, roi, binning, exposure_us, gain_db) -> None:
        cam = self._cam
        # Order matters: binning changes the region's bounds, the format changes the payload.
        if binning is not None:
            bx, by = (int(b) for b in binning)
            if not self._call("is_binning_available", cam.is_binning_available):
                raise CameraError(f"camera {self.name} has no binning (BinningHorizontal/BinningVertical)")
            self._check_range("horizontal binning", bx, self._call("binning bounds", cam.get_x_binning_bounds), "px")
            self._check_range("vertical binning", by, self._call("binning bounds", cam.get_y_binning_bounds), "px")
            self._call(f"setting binning {bx}x{by}", cam.set_binning, bx, by)
        if pixel_format is not None:
            offered = list(self._call("listing pixel formats", cam.dup_available_pixel_formats_as_strings) or [])
            if pixel_format not in offered:
                raise CameraError(
                    f"camera {self.name} offers no pixel format {pixel_format!r}; it offers {', '.join(offered)}"
                )
            self._call(f"setting pixel format {pixel_format}", cam.set_pixel_format_from_string, pixel_format)
        readback_format = self._call("reading the pixel format", cam.get_pixel_format_as_string)
        if readback_format not in PIXEL_FORMATS:
            supported = [f for f in (self._call("listing pixel formats", cam.dup_available_pixel_formats_as_strings) or [])
                         if f in PIXEL_FORMATS]
            raise CameraError(
                f"camera {self.name} is set to pixel format {readback_format!r}, which lfrig cannot decode; "
                f"pass --pixel-format with one of {', '.join(supported) or '(none offered)'}"
            )
        if roi is not None:
            x, y, w, h = (int(c) for c in roi)
            self._check_range("ROI width", w, self._call("width bounds", cam.get_width_bounds), "px")
            self._check_range("ROI height", h, self._call("height bounds", cam.get_height_bounds), "px")
            sensor = self._call("reading the sensor size", cam.get_sensor_size)
            if x < 0 or y < 0:
                raise CameraError(f"camera {self.name}: ROI offset ({x}, {y}) must be >= 0")
            dx, dy = (1, 1)
            if self._call("is_binning_available", cam.is_binning_available):
                dx, dy = (max(1, int(b)) for b in self._call("reading the binning", cam.get_binning))
            width, height = sensor.width // dx, sensor.height // dy  # the region is in binned pixels
            if x + w > width or y + h > height:
                raise CameraError(
                    f"camera {self.name}: ROI ({x}, {y}, {w}, {h}) reaches beyond the {width}x{height} sensor"
                    f"{f' (binned {dx}x{dy})' if (dx, dy) != (1, 1) else ''}; give offset + size within it"
                )
            self._call(f"setting the ROI {x},{y} {w}x{h}", cam.set_region, x, y, w, h)
            got = self._call("reading the region", cam.get_region)
            if (got.x, got.y, got.width, got.height) != (x, y, w, h):
                raise CameraError(
                    f"camera {self.name}: ROI ({x}, {y}, {w}, {h}) was set as ({got.x}, {got.y}, {got.width}, "
                    f"{got.height}); use offsets and sizes that are multiples of the camera's increments "
                    f"and fit the {sensor.width}x{sensor.height} sensor (binned: divide by the binning)"
                )
        if exposure_us is not None:
            if not self._call("is_exposure_time_available", cam.is_exposure_time_available):
                raise CameraError(f"camera {self.name} has no exposure time feature (ExposureTime)")
            self._check_range("exposure", float(exposure_us), self._call("exposure bounds", cam.get_exposure_time_bounds), "us")
            if self._call("is_exposure_auto_available", cam.is_exposure_auto_available):
                self._call("switching auto exposure off", cam.set_exposure_time_auto, self._aravis.Auto.OFF)
            self._call(f"setting exposure {exposure_us} us", cam.set_exposure_time, float(exposure_us))
        if gain_db is not None:
            if not self._call("is_gain_available", cam.is_gain_available):
                raise CameraError(f"camera {self.name} has no gain feature (Gain/GainRaw)")
            if not self._has("Gain"):
                log.warning("camera %s has no Gain feature in dB; %s is taken as raw GainRaw steps", self.name, gain_db)
            self._check_range("gain", float(gain_db), self._call("gain bounds", cam.get_gain_bounds), self._gain_unit())
            if self._call("is_gain_auto_available", cam.is_gain_auto_available):
                self._call("switching auto gain off", cam.set_gain_auto, self._aravis.Auto.OFF)
            self._call(f"setting gain {gain_db}", cam.set_gain, float(gain_db))
        self._configure_trigger()
        self._call("setting continuous acquisition", cam.set_acquisition_mode, self._aravis.AcquisitionMode.CONTINUOUS)
        readback = self._readback()
        for key, unit in (("exposure_us", "us"), ("gain", self._gain_unit())):
            want = self.requested["gain_db" if key == "gain" else key]
            have = readback.get(key)
            if want is not None and have is not None and abs(have - want) > 1e-6 * max(1.0, abs(want)):
                log.warning("camera %s: %s requested %s %s, reads back %s", self.name, key, want, unit, have)

    def _has(self, feature: str) -> bool:
        try:
            return bool(self._cam.is_feature_available(feature))
        except self._gerror:
            return False

    def _gain_unit(self) -> str:
        return "dB" if self._has("Gain") else "raw"

    def _configure_trigger(self) -> None:
        cam = self._cam
        if self.trigger_mode == "free":
            self._call("clearing triggers", cam.clear_triggers)
            return
        sources = list(self._call("listing trigger sources", cam.dup_available_trigger_sources) or [])
        source = "Software" if self.trigger_mode == "software" else self.trigger_mode
        if source not in sources:
            what = "software trigger" if source == "Software" else f"trigger line {source!r}"
            raise CameraError(
                f"camera {self.name} has no {what}; its trigger sources are {', '.join(sources) or '(none)'} "
                "(use --trigger free for a free-running camera)"
            )
        # set_trigger: TriggerSelector=FrameStart, TriggerMode=On, TriggerActivation=RisingEdge, the source.
        self._call(f"setting the trigger to {source}", cam.set_trigger, source)

    def _start(self) -> None:
        cam = self._cam
        payload = int(self._call("reading the payload size", cam.get_payload))
        self._stream = self._call("creating the stream", cam.create_stream, None, None)
        if self._stream is None:
            raise CameraError(f"camera {self.name}: could not create a stream")
        for _ in range(self._buffers):
            self._stream.push_buffer(self._aravis.Buffer.new_allocate(payload))
        self._payload = payload
        self._call("starting acquisition", cam.start_acquisition)
        self._acquiring = True
        region = self._call("reading the region", cam.get_region)
        self._geometry = (int(region.width), int(region.height))
        self._format = self._call("reading the pixel format", cam.get_pixel_format_as_string)
        self._format_code = int(self._call("reading the pixel format", cam.get_pixel_format))

    # ---- frames ------------------------------------------------------------------------------

    def _flush(self) -> int:
        """Give every frame already in the output queue back to the pool; returns how many."""
        count = 0
        while True:
            buffer = self._stream.try_pop_buffer()
            if buffer is None:
                return count
            self._stream.push_buffer(buffer)
            count += 1

    def _fire(self) -> None:
        if self.trigger_mode == "software":
            try:
                self._cam.software_trigger()
            except self._gerror as error:
                raise CameraError(
                    f"camera {self.name}: software trigger failed: {_gerror_message(error)}; the camera does not "
                    "answer: check its power and cable (GigE: network link and address)"
                ) from None
        elif self.trigger_mode != "free" and self.hardware_trigger is not None:
            self.hardware_trigger(True)
            self.clock.sleep(self.trigger_pulse_s)
            self.hardware_trigger(False)

    def trigger(self) -> np.ndarray:
        """A frame whose exposure began after this call began; see the module docstring.

        Raises
        ------
        CameraTimeoutError
            No fresh complete frame arrived within ``exposure + timeout_s``.
        """
        if self._stream is None or self._cam is None:
            raise CameraError(f"camera {self.name} is closed")
        self._flush()
        exposure_us = self._exposure_us()
        margin_ns = 0  # triggered: the camera sends a frame only for a trigger, and the queue is empty now
        if self.trigger_mode == "free":
            rate = self._frame_rate()
            margin_ns = int(exposure_us * 1e3) + (int(1e9 / rate) if rate else 0)
        t0_ns = time.time_ns()
        self._fire()
        deadline = time.monotonic() + self.timeout_s + exposure_us * 1e-6
        stale = failed = 0
        while True:
            buffer = None
            while buffer is None and (remaining := deadline - time.monotonic()) > 0:
                # short waits, so that a Ctrl-C (handled between calls into Aravis) is seen promptly
                buffer = self._stream.timeout_pop_buffer(max(1, int(min(remaining, 0.1) * 1e6)))
            if buffer is None:
                self._stale_dropped += stale
                self._failed_buffers += failed
                raise CameraTimeoutError(self._timeout_message(stale, failed))
            try:
                status = buffer.get_status()
                if status != self._aravis.BufferStatus.SUCCESS:
                    failed += 1
                    log.warning("camera %s: incomplete frame (%s), waiting for the next", self.name, status.value_nick)
                    continue
                received_ns = int(buffer.get_system_timestamp())
                if received_ns and received_ns < t0_ns + margin_ns:
                    stale += 1
                    continue
                image = self._decode(buffer)
                self._last = {
                    "frame_id": int(buffer.get_frame_id()),
                    "timestamp_ns": int(buffer.get_timestamp()),
                    "received_ns": received_ns,
                    "trigger_ns": t0_ns,
                    "stale_dropped": stale,
                    "incomplete_dropped": failed,
                }
            finally:
                self._stream.push_buffer(buffer)
            self._frames += 1
            self._stale_dropped += stale
            self._failed_buffers += failed
            return image

    def _timeout_message(self, stale: int, failed: int) -> str:
        waited = f"{self.timeout_s:g} s"
        detail = []
        if stale:
            detail.append(f"{stale} stale frame(s) dropped")
        if failed:
            detail.append(f"{failed} incomplete frame(s)")
        extra = f" ({'; '.join(detail)})" if detail else ""
        if self.trigger_mode == "software":
            hint = "check the cable/network and that nothing else controls the camera"
        elif self.trigger_mode == "free":
            hint = "check the cable/network and the camera's frame rate (AcquisitionFrameRate)"
        else:
            hint = (f"is {self.trigger_mode} wired to the trigger output"
                    + (" (the stage's M8)" if self.hardware_trigger is not None else "") + " and firing?")
        return f"camera {self.name} delivered no fresh frame within {waited} after the trigger{extra}; {hint}"

    def _decode(self, buffer: Any) -> np.ndarray:
        code = int(buffer.get_image_pixel_format())
        if code != self._format_code:
            raise CameraError(
                f"camera {self.name} sent pixel format 0x{code:08x}, expected {self._format} (0x{self._format_code:08x})"
            )
        width, height = int(buffer.get_image_width()), int(buffer.get_image_height())
        return decode_frame(buffer.get_data(), pixel_format=self._format, width=width, height=height)

    def _exposure_us(self) -> float:
        try:
            return float(self._cam.get_exposure_time())
        except self._gerror:
            return 0.0

    def _frame_rate(self) -> float | None:
        try:
            if self._cam.is_frame_rate_available():
                return float(self._cam.get_frame_rate())
        except self._gerror:
            pass
        return None

    # ---- read-back -------------------------------------------------------------------------------

    def _readback(self) -> dict[str, Any]:
        cam = self._cam

        def read(function: Callable[..., Any], *args: Any) -> Any:
            try:
                return function(*args)
            except self._gerror:
                return None

        region = read(cam.get_region)
        binning = read(cam.get_binning) if read(cam.is_binning_available) else None
        trigger_mode = read(cam.get_string, "TriggerMode") if self._has("TriggerMode") else None
        return {
            "pixel_format": read(cam.get_pixel_format_as_string),
            "roi": [region.x, region.y, region.width, region.height] if region is not None else None,
            "binning": [binning.dx, binning.dy] if binning is not None else None,
            "exposure_us": read(cam.get_exposure_time),
            "gain": read(cam.get_gain),
            "gain_unit": self._gain_unit(),
            "trigger_mode": trigger_mode,
            "trigger_source": read(cam.get_trigger_source) if trigger_mode == "On" else None,
            "frame_rate_hz": self._frame_rate(),
        }

    def settings(self) -> dict[str, Any]:
        """Requested and read-back settings plus the last frame's id and times (recorded per frame).

        ``readback`` holds ``pixel_format``, ``roi`` ``[x, y, w, h]``, ``binning`` ``[h, v]``,
        ``exposure_us``, ``gain`` (in ``gain_unit``), ``trigger_mode``, ``trigger_source``, ``frame_rate_hz``.
        """
        cam = self._cam
        fmt = PIXEL_FORMATS.get(getattr(self, "_format", ""), None)
        return {
            "driver": "aravis",
            "device_id": self.name,
            "vendor": cam.get_vendor_name(),
            "model": cam.get_model_name(),
            "serial": cam.get_device_serial_number(),
            "requested": dict(self.requested),
            "readback": self._readback(),
            "trigger": self.trigger_mode,
            "hardware_trigger": self.hardware_trigger is not None,
            "significant_bits": fmt.bits if fmt else None,
            "bit_shift": (16 - fmt.bits) if fmt and fmt.bits not in (8, 16) else 0,
            "frames": self._frames,
            "stale_dropped_total": self._stale_dropped,
            "incomplete_dropped_total": self._failed_buffers,
            "last_frame": dict(self._last),
        }

    @property
    def device(self) -> Any:
        """The underlying ``Aravis.Camera`` (for features lfrig does not wrap)."""
        return self._cam

    def close(self) -> None:
        if getattr(self, "_acquiring", False):
            try:
                self._cam.stop_acquisition()
            except Exception:  # the camera may be gone; closing must not fail
                pass
            self._acquiring = False
        self._stream = None  # dropping the last references stops Aravis's stream thread and frees the buffers
        self._cam = None

    def __enter__(self) -> "AravisCamera":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_aravis(
    spec: str,
    *,
    pixel_format: str | None = None,
    roi: tuple[int, int, int, int] | None = None,
    binning: int | None = None,
    exposure_us: float | None = None,
    gain_db: float | None = None,
    trigger: str = "software",
    hardware_trigger: Callable[[bool], None] | None = None,
    timeout_s: float = 5.0,
    clock: Clock | None = None,
) -> tuple[AravisCamera, dict[str, Any]]:
    """Open ``--camera aravis:[DEVICE_ID]``; returns the camera and the requested settings that a
    resumed capture must match (the timeout is not among them: it may change between runs)."""
    camera = AravisCamera(parse_spec(spec), pixel_format=pixel_format, roi=roi, binning=binning,
                          exposure_us=exposure_us, gain_db=gain_db, trigger=trigger,
                          hardware_trigger=hardware_trigger, timeout_s=timeout_s, clock=clock)
    request = {"device": spec, "pixel_format": pixel_format, "roi": list(roi) if roi else None, "binning": binning,
               "exposure_us": exposure_us, "gain_db": gain_db, "trigger": camera.trigger_mode,
               "hw_trigger": hardware_trigger is not None}
    return camera, request


# --------------------------------------------------------------------------------------------------
# Description (lfrig camera info)


def describe(camera: AravisCamera, *, all_features: bool = False) -> dict[str, Any]:
    """What the camera is and offers: identity, sensor, formats, ROI/binning/exposure/gain bounds,
    triggers; with ``all_features`` every GenICam feature of its feature tree with its current value."""
    cam = camera.device
    gerror = camera._gerror

    def read(function: Callable[..., Any], *args: Any) -> Any:
        try:
            return function(*args)
        except gerror:
            return None

    def bounds(function: Callable[..., Any]) -> list[float] | None:
        b = read(function)
        return [b.min, b.max] if b is not None else None

    sensor = read(cam.get_sensor_size)
    info: dict[str, Any] = {
        "device_id": camera.name,
        "vendor": read(cam.get_vendor_name),
        "model": read(cam.get_model_name),
        "serial": read(cam.get_device_serial_number),
        "protocol": "GigE Vision" if read(cam.is_gv_device) else "USB3 Vision" if read(cam.is_uv_device) else "other",
        "sensor_px": [sensor.width, sensor.height] if sensor is not None else None,
        "pixel_formats": list(read(cam.dup_available_pixel_formats_as_strings) or []),
        "pixel_formats_lfrig_decodes": [f for f in (read(cam.dup_available_pixel_formats_as_strings) or []) if f in PIXEL_FORMATS],
        "width_px": bounds(cam.get_width_bounds),
        "height_px": bounds(cam.get_height_bounds),
        "binning_x": bounds(cam.get_x_binning_bounds) if read(cam.is_binning_available) else None,
        "binning_y": bounds(cam.get_y_binning_bounds) if read(cam.is_binning_available) else None,
        "exposure_us": bounds(cam.get_exposure_time_bounds) if read(cam.is_exposure_time_available) else None,
        "gain": bounds(cam.get_gain_bounds) if read(cam.is_gain_available) else None,
        "gain_unit": camera._gain_unit(),
        "triggers": list(read(cam.dup_available_triggers) or []),
        "trigger_sources": list(read(cam.dup_available_trigger_sources) or []),
        "software_trigger": bool(read(cam.is_software_trigger_supported)),
        "current": camera._readback(),
    }
    if all_features:
        info["features"] = feature_tree(camera)
    return info


def feature_tree(camera: AravisCamera) -> dict[str, Any]:
    """``{category: {feature: value-as-string, subcategory: {...}}}`` from the GenICam ``Root``."""
    device = camera.device.get_device()
    genicam = device.get_genicam()
    gerror = camera._gerror

    def walk(name: str, depth: int) -> Any:
        node = genicam.get_node(name)
        if node is None:
            return None
        if hasattr(node, "get_features") and depth < 16:
            return {child: walk(child, depth + 1) for child in (node.get_features() or [])}
        if not camera._has(name):
            return "(not available)"
        try:
            value = node.get_value_as_string()
        except gerror:
            return "(not readable)"
        except (AttributeError, TypeError):
            return "(command)"
        unit = None
        if hasattr(node, "get_unit"):
            try:
                unit = node.get_unit()
            except gerror:
                unit = None
        return f"{value} {unit}" if unit else value

    return walk("Root", 0) or {}
