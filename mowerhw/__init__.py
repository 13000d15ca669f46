"""mowerhw: wire-free, GPS-free containment for a robotic mower (after Yang et al., IROS 2013).

Packages: ``mowerhw`` holds computation and the runtime, ``drivers`` the device I/O
(DESIGN.md §2). Importing this package is cheap: nothing heavy is imported here.
"""

__version__ = "0.1.0"
