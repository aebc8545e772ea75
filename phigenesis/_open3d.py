"""Imports Open3D, loading the libusb-1.0 it links against from the ``libusb-package`` wheel.

Open3D's Linux wheel needs the system library libusb-1.0, which minimal machines lack; the
``libusb-package`` dependency ships it, and loading it globally with ctypes first lets Open3D
import without a system package.
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib
from types import ModuleType

_module: ModuleType | None = None


def open3d() -> ModuleType:
    """The ``open3d`` module, imported once."""
    global _module
    if _module is None:
        with contextlib.suppress(ImportError):  # without the wheel, a system libusb-1.0 may serve
            # optional wheel: only where pip installed it
            import libusb_package

            path = libusb_package.get_library_path()
            if path is not None:
                ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
        _module = importlib.import_module("open3d")
    return _module
