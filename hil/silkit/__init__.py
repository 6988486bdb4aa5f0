"""Vector SIL Kit: its runtime (the library and the registry, from the silkit-py wheel), a ctypes binding of the
parts of its stable C API the rig uses, and participants built on it.

SIL Kit's own Python package (silkit-py 1.0.5) has no network simulator and cannot build a CAN frame, so the rig
calls the C API of the ``libSilKit.so`` it bundles directly (``capi``). The wheel is for CPython 3.12, but the
library and the registry are plain native code: ``hil silkit install`` fetches the wheel with pip for 3.12 and
unpacks them, so the rig keeps running on 3.11 (``runtime``)."""
