"""A one-line notice when numba compiles the numerical kernels (ray casting, box overlaps, KITTI matching).

They are compiled on their first call after an install or a change and then cached on disk
(``cache=True``: next to the sources, or in ``NUMBA_CACHE_DIR``). Measured on 2 busy cores with an
empty cache against the cached one: a 3-frame ``simulate`` 15.7 s against 3.6 s, ``evaluate`` of it
17.8 s against 2.7 s. Without a word, that first wait looks like a hang.
"""
from __future__ import annotations

import sys

NOTICE = ("note: compiling the numerical kernels (numba) once for this install: this first run takes 10-20 s "
          "longer; later runs load them from the disk cache")


def _write(text: str) -> None:
    """On stderr, on its own line above any open progress bar."""
    from tqdm import tqdm
    tqdm.write(text, file=sys.stderr)


class _State:
    write = None  # the writer of the notice, None before announce_compiles
    said = False


def announce_compiles(write=_write) -> None:
    """From now on, the first numba compile of this process calls ``write(NOTICE)``, once (loads from
    the disk cache are no compiles and say nothing); a second call only changes the writer."""
    from numba.core import event

    class Notice(event.Listener):
        def on_start(self, ev) -> None:
            if not _State.said:
                _State.said = True
                _State.write(NOTICE)

        def on_end(self, ev) -> None:
            pass

    if _State.write is None:
        event.register("numba:compile", Notice())
    _State.write = write
