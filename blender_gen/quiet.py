"""Silence chatter from Blender's C code (and optionally Python) on stdout."""
from __future__ import annotations

import contextlib
import io
import os
import sys


@contextlib.contextmanager
def quiet_stdout(python_too: bool = False):
    """Redirect file descriptor 1 (Blender's 'Saved: ...' lines) to /dev/null; with
    `python_too`, Python-level prints as well (the glTF importer's log)."""
    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        with contextlib.redirect_stdout(io.StringIO()) if python_too else contextlib.nullcontext():
            yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)
