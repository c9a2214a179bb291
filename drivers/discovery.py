"""What is plugged in: serial ports (with what they probably are), V4L2 cameras and their modes, OAK devices.

``vbnav find`` prints these; ``vbnav doctor`` uses the serial part. Everything
here only looks: ports are listed by pyserial (sysfs), cameras are asked for
their formats with the V4L2 enumeration ioctls (no streaming), OAK devices by
depthai's device search. None of them present is a normal result.
"""
from __future__ import annotations

import ctypes
import fcntl
import glob
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

from vbnav.drivers.errors import InputError

# USB vendor:product -> what it probably is on a robot (the same chip serves other gadgets too).
USB_IDS = {
    (0x0403, 0x6014): "ROBOTIS U2D2 (FTDI FT232H): Dynamixel bus adapter",
    (0x0403, 0x6001): "FTDI FT232R: USB2Dynamixel or a generic USB-serial cable",
    (0x0403, 0x6010): "FTDI FT2232: dual USB-serial",
    (0x1209, 0x0D32): "ODrive v3 (native USB + CDC serial)",
    (0x1209, 0x0D33): "ODrive (USB CDC serial)",
    (0x0483, 0x5740): "STM32 virtual COM port (ROBOTIS OpenCR, other STM32 boards)",
    (0x10C4, 0xEA60): "Silicon Labs CP210x USB-serial",
    (0x1A86, 0x7523): "WCH CH340 USB-serial",
    (0x2341, 0x0043): "Arduino Uno",
}


def check_device(port: str, expected: str, hint: str = "") -> None:
    """Raise InputError (naming ``--port``) unless ``port`` is a character device (a serial adapter, an
    emulator's pty or a link to one); ``expected`` says what it should be, ``hint`` is added to both
    messages (" (vbnav find lists the serial ports)")."""
    import stat
    try:
        mode = os.stat(port).st_mode
    except FileNotFoundError:
        raise InputError(f"--port {port}: no such device{hint}") from None
    except OSError as exc:       # a folder on the way that may not be read
        raise InputError(f"--port {port}: {exc.strerror}{hint}") from None
    if not stat.S_ISCHR(mode):
        raise InputError(f"--port {port}: is not a device ({'a folder' if stat.S_ISDIR(mode) else 'a file'}); "
                         f"expected {expected}{hint}")


def usb_kind(vid: Optional[int], pid: Optional[int]) -> str:
    if vid is None:
        return "not USB (built-in UART or virtual)"
    return USB_IDS.get((vid, pid), "unknown USB-serial device")


@dataclass
class SerialPort:
    device: str                     # /dev/ttyUSB0
    by_id: list[str]                # /dev/serial/by-id/... links to it (stable across replugging)
    vid: Optional[int]
    pid: Optional[int]
    kind: str                       # what it probably is
    description: str = ""
    serial_number: str = ""
    latency_timer_ms: Optional[int] = None   # FTDI adapters: /sys/bus/usb-serial/devices/<tty>/latency_timer

    @property
    def usb_id(self) -> str:
        return f"{self.vid:04x}:{self.pid:04x}" if self.vid is not None else "-"


def latency_timer_path(device: str, sysfs: str = "/sys") -> Path:
    """Where the FTDI latency timer of ``device`` (its real name, e.g. /dev/ttyUSB0) is set."""
    return Path(sysfs) / "bus/usb-serial/devices" / Path(os.path.realpath(device)).name / "latency_timer"


def read_latency_timer(device: str, sysfs: str = "/sys") -> Optional[int]:
    try:
        return int(latency_timer_path(device, sysfs).read_text().strip())
    except (OSError, ValueError):
        return None


def by_id_links(by_id_dir: str = "/dev/serial/by-id") -> dict[str, list[str]]:
    """real device path -> the stable links pointing at it."""
    out: dict[str, list[str]] = {}
    for link in sorted(glob.glob(os.path.join(by_id_dir, "*"))):
        out.setdefault(os.path.realpath(link), []).append(link)
    return out


def serial_ports(extra: tuple[str, ...] = (), by_id_dir: str = "/dev/serial/by-id",
                 sysfs: str = "/sys") -> list[SerialPort]:
    """USB and built-in serial ports pyserial sees, plus ``extra`` device paths (an emulator's pty)."""
    from serial.tools import list_ports
    links = by_id_links(by_id_dir)
    found = []
    for p in sorted(list_ports.comports(), key=lambda p: p.device):
        found.append(SerialPort(p.device, links.get(os.path.realpath(p.device), []), p.vid, p.pid,
                                usb_kind(p.vid, p.pid), p.description or "", p.serial_number or "",
                                read_latency_timer(p.device, sysfs)))
    for dev in extra:
        if any(os.path.realpath(dev) == os.path.realpath(f.device) for f in found):
            continue
        if os.path.exists(dev):
            found.append(SerialPort(dev, links.get(os.path.realpath(dev), []), None, None,
                                    "not USB (a pseudo-terminal or built-in UART)", "", "", None))
    return found


# -- V4L2 ------------------------------------------------------------------------------------------
def _iowr(nr: int, size: int) -> int:
    return (3 << 30) | (size << 16) | (ord("V") << 8) | nr


class _Capability(ctypes.Structure):
    _fields_ = [("driver", ctypes.c_char * 16), ("card", ctypes.c_char * 32), ("bus_info", ctypes.c_char * 32),
                ("version", ctypes.c_uint32), ("capabilities", ctypes.c_uint32), ("device_caps", ctypes.c_uint32),
                ("reserved", ctypes.c_uint32 * 3)]


class _FmtDesc(ctypes.Structure):
    _fields_ = [("index", ctypes.c_uint32), ("type", ctypes.c_uint32), ("flags", ctypes.c_uint32),
                ("description", ctypes.c_char * 32), ("pixelformat", ctypes.c_uint32),
                ("mbus_code", ctypes.c_uint32), ("reserved", ctypes.c_uint32 * 3)]


class _FrmSize(ctypes.Structure):
    _fields_ = [("index", ctypes.c_uint32), ("pixel_format", ctypes.c_uint32), ("type", ctypes.c_uint32),
                ("u", ctypes.c_uint32 * 6), ("reserved", ctypes.c_uint32 * 2)]


class _FrmIval(ctypes.Structure):
    _fields_ = [("index", ctypes.c_uint32), ("pixel_format", ctypes.c_uint32), ("width", ctypes.c_uint32),
                ("height", ctypes.c_uint32), ("type", ctypes.c_uint32), ("u", ctypes.c_uint32 * 6),
                ("reserved", ctypes.c_uint32 * 2)]


VIDIOC_QUERYCAP = (2 << 30) | (ctypes.sizeof(_Capability) << 16) | (ord("V") << 8) | 0
VIDIOC_ENUM_FMT = _iowr(2, ctypes.sizeof(_FmtDesc))
VIDIOC_ENUM_FRAMESIZES = _iowr(74, ctypes.sizeof(_FrmSize))
VIDIOC_ENUM_FRAMEINTERVALS = _iowr(75, ctypes.sizeof(_FrmIval))
V4L2_BUF_TYPE_VIDEO_CAPTURE = 1
V4L2_CAP_VIDEO_CAPTURE = 0x1
V4L2_CAP_DEVICE_CAPS = 0x80000000
_DISCRETE = 1


def fourcc(value: int) -> str:
    return "".join(chr((value >> (8 * i)) & 0xFF) for i in range(4))


@dataclass
class CameraMode:
    fourcc: str
    description: str
    sizes: list[tuple[int, int, list[float]]] = field(default_factory=list)   # (width, height, rates Hz)


@dataclass
class V4L2Device:
    device: str                     # /dev/video0
    name: str                       # from sysfs
    by_id: list[str]
    capture: Optional[bool] = None  # a capture node (UVC cameras also have metadata nodes)
    modes: list[CameraMode] = field(default_factory=list)
    error: str = ""                 # why it could not be asked (permissions, busy)


def _enum(fd: int, request: int, struct) -> bool:
    try:
        fcntl.ioctl(fd, request, struct)
        return True
    except OSError:
        return False                # EINVAL ends every V4L2 enumeration


def camera_modes(fd: int) -> list[CameraMode]:
    """Formats, discrete sizes and their frame rates of a capture device (VIDIOC_ENUM_*)."""
    modes = []
    fmt = _FmtDesc(type=V4L2_BUF_TYPE_VIDEO_CAPTURE)
    while _enum(fd, VIDIOC_ENUM_FMT, fmt):
        mode = CameraMode(fourcc(fmt.pixelformat), fmt.description.decode(errors="replace"))
        size = _FrmSize(pixel_format=fmt.pixelformat)
        while _enum(fd, VIDIOC_ENUM_FRAMESIZES, size):
            if size.type != _DISCRETE:      # stepwise/continuous: report the range's ends
                mode.sizes.append((size.u[0], size.u[3], []))
                mode.sizes.append((size.u[1], size.u[4], []))
                break
            w, h = size.u[0], size.u[1]
            rates = []
            ival = _FrmIval(pixel_format=fmt.pixelformat, width=w, height=h)
            while _enum(fd, VIDIOC_ENUM_FRAMEINTERVALS, ival):
                if ival.type == _DISCRETE and ival.u[0]:
                    rates.append(round(ival.u[1] / ival.u[0], 2))
                ival.index += 1
            mode.sizes.append((w, h, rates))
            size.index += 1
        modes.append(mode)
        fmt.index += 1
    return modes


def v4l2_devices(sysfs: str = "/sys", dev: str = "/dev", by_id_dir: str = "/dev/v4l/by-id") -> list[V4L2Device]:
    """Every /sys/class/video4linux node with its name; capture nodes with their formats, sizes and rates."""
    links: dict[str, list[str]] = {}
    for link in sorted(glob.glob(os.path.join(by_id_dir, "*"))):
        links.setdefault(os.path.basename(os.path.realpath(link)), []).append(link)
    out = []
    for node in sorted(Path(sysfs, "class/video4linux").glob("video*"), key=lambda p: int(p.name[5:] or 0)):
        try:
            name = (node / "name").read_text().strip()
        except OSError:
            name = "?"
        d = V4L2Device(os.path.join(dev, node.name), name, links.get(node.name, []))
        try:
            fd = os.open(d.device, os.O_RDWR | os.O_NONBLOCK)
        except OSError as exc:
            d.error = f"cannot open: {exc.strerror}"
            out.append(d)
            continue
        try:
            cap = _Capability()
            if _enum(fd, VIDIOC_QUERYCAP, cap):
                caps = cap.device_caps if cap.capabilities & V4L2_CAP_DEVICE_CAPS else cap.capabilities
                d.capture = bool(caps & V4L2_CAP_VIDEO_CAPTURE)
                if d.capture:
                    d.modes = camera_modes(fd)
            else:
                d.error = "not a V4L2 device (VIDIOC_QUERYCAP failed)"
        finally:
            os.close(fd)
        out.append(d)
    return out


# -- USB identity of a device node --------------------------------------------------------------------
@dataclass(frozen=True)
class UsbIdentity:
    vendor: str                     # "0403", as udev's ATTRS{idVendor}
    product: str                    # "6014"
    serial: str                     # the USB iSerialNumber, "" when the device has none


def usb_identity(device: str, sysfs: str = "/sys") -> Optional[UsbIdentity]:
    """The USB device behind a serial or V4L2 node (``/dev/ttyUSB0``, a by-id link, ``/dev/video0``): its
    vendor, product and serial number from sysfs, or None when it is not there or not on USB."""
    name = os.path.basename(os.path.realpath(device))
    for subsystem in ("tty", "video4linux"):
        node = Path(sysfs, "class", subsystem, name, "device")
        if not node.exists():
            continue
        d = node.resolve()
        while d != d.parent:        # up from the interface to the USB device, which has idVendor
            if (d / "idVendor").is_file():
                def attr(a: str) -> str:
                    try:
                        return (d / a).read_text().strip()
                    except OSError:
                        return ""
                return UsbIdentity(attr("idVendor"), attr("idProduct"), attr("serial"))
            d = d.parent
        return None
    return None


# -- OAK ---------------------------------------------------------------------------------------------
def oak_devices(timeout_s: float = 3.0) -> tuple[Optional[list[str]], str]:
    """(descriptions of the OAK devices found, note). None when depthai is not installed or the search
    did not return in time; the note says which."""
    from vbnav.drivers import registry
    if registry.missing_sdk(registry.CAMERAS, "oak"):
        return None, "depthai is not installed (pip install 'vbnav[oak]')"
    from vbnav.drivers.oak_camera import describe, list_devices
    found = list_devices(timeout_s)
    if found is None:
        return None, f"the device search did not return within {timeout_s:g} s"
    return [describe(info) for info in found], ""
