"""The one place open3d is imported.

open3d's wheel links against libusb-1.0.so.0, which minimal Debian/Ubuntu images lack. When the
system library is missing we preload the copy shipped by the `libusb-package` wheel, so that a
plain `pip install` is enough on a fresh machine (no root, no apt).
"""

from __future__ import annotations

import ctypes
import importlib


def _load_open3d():
    try:
        return importlib.import_module("open3d")
    except ImportError as exc:
        if "libusb" not in str(exc):
            raise
        import libusb_package

        lib = libusb_package.get_library_path()
        if lib is None:
            raise
        ctypes.CDLL(str(lib), mode=ctypes.RTLD_GLOBAL)
        return importlib.import_module("open3d")


o3d = _load_open3d()
