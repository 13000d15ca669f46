"""mowerhw: wire-free, GPS-free containment for a robotic mower (after Yang et al., IROS 2013).

Packages: ``mowerhw`` holds computation and the runtime, ``drivers`` the device I/O
(docs/design.md §2). Importing this package is cheap: nothing heavy is imported here.
"""

import os as _os

# The estimators multiply small matrices hundreds of times a second. A multi-threaded BLAS
# gains nothing there, and its worker threads spin between calls: measured in the daemon,
# one OpenBLAS thread burned 40 % of a core. One BLAS thread unless the user says otherwise
# (set before numpy is first imported; the front end's OpenCV threads are set in the daemon).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")

__version__ = "0.1.0"
