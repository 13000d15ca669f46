"""Device I/O: bytes on the wire ↔ typed, timestamped samples (docs/design.md §2, §7).

One package per device kind, each with one small interface, the real driver and a mock that
speaks the same wire format over a real transport (the python-can way: choose the backend by
config, test against the mock):

* :mod:`drivers.imu` — :class:`~drivers.imu.base.ImuSource`; the VN-100 (serial), its mock on
  a pseudo-terminal;
* :mod:`drivers.can` — python-can's bus is the interface (``virtual`` in tests); ground speed
  in, permit / halt out, mock speed sensor and mock mower controller;
* :mod:`drivers.camera` — :class:`~drivers.camera.base.CameraSource`; V4L2, a socket stream,
  a synthetic mock.

Drivers never import estimators.
"""
