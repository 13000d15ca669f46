"""The map loader child of :func:`mowerhw.runtime.mapfiles.load_map_isolated`: parses and
checks one map file in its own interpreter, so a hostile file costs this process (memory,
time, recursion), never the daemon's event loop.

    python -m mowerhw.runtime.maploader PATH MAX_BYTES

writes one pickled ``("ok", LawnMap)`` or ``("error", message)`` to stdout, whatever happens.
"""

from __future__ import annotations

import pickle
import sys
from pathlib import Path
from typing import Any


def main(path: str, max_bytes: int) -> None:
    try:
        from mowerhw.map import MapError, load

        try:
            result: tuple[str, Any] = ("ok", load(Path(path), max_bytes))
        except MapError as exc:
            result = ("error", str(exc))
    except BaseException as exc:  # MemoryError, RecursionError, a bug: say so, do not hang
        result = ("error", f"{path}: cannot load the map ({type(exc).__name__}: {exc})"[:500])
    sys.stdout.buffer.write(pickle.dumps(result))
    sys.stdout.flush()


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]))
