"""Silence chatter from Blender's C code (and optionally Python) on stdout, or drop expected lines."""
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


@contextlib.contextmanager
def without_lines(*fragments: str):
    """Run a block with file descriptors 1 and 2 captured, then pass on every line that contains
    none of `fragments`: drops an expected warning of Blender's C code (its log writes to stdout),
    keeps every other message."""
    import tempfile

    streams = ((1, sys.stdout), (2, sys.stderr))
    saved, tmps = [], []
    for fd, stream in streams:
        stream.flush()
        saved.append(os.dup(fd))
        tmps.append(tempfile.TemporaryFile())
        os.dup2(tmps[-1].fileno(), fd)
    try:
        yield
    finally:
        for (fd, stream), keep, tmp in zip(streams, saved, tmps):
            stream.flush()
            os.dup2(keep, fd)
            os.close(keep)
            tmp.seek(0)
            for line in tmp.read().decode(errors="replace").splitlines(keepends=True):
                if not any(f in line for f in fragments):
                    stream.write(line)
            stream.flush()
            tmp.close()
