"""How the command lines report errors: expected ones in one line, bugs with their traceback.

Bad input (a ValueError of ours: DatasetError, ConfigError, RulesError, ...) and failed
I/O (OSError: disk full, read-only folder) are the user's to fix, so they print one line
naming the file or option. Anything else is a bug and keeps its traceback. Set
IAE_DEBUG=1 to see the traceback of an expected error too.
"""
from __future__ import annotations

import os
from contextlib import contextmanager
from typing import Iterator

DEBUG_ENV = "IAE_DEBUG"
EXPECTED: tuple[type[BaseException], ...] = (ValueError, OSError)


def first_line(exc: BaseException) -> str:
    """An exception as one line: an OSError's file and reason, else its message's first line."""
    if isinstance(exc, OSError) and exc.strerror:
        return f"{exc.filename}: {exc.strerror}" if exc.filename else exc.strerror
    text = str(exc).strip()
    line = text.splitlines()[0] if text else type(exc).__name__
    # click prints its own "Error: "; a library's message that starts with one would read "Error: Error: ..."
    while line.lower().startswith("error:"):
        line = line[len("error:"):].strip() or type(exc).__name__
    return line


@contextmanager
def one_line_errors(expected: tuple[type[BaseException], ...] = EXPECTED) -> Iterator[None]:
    import click

    try:
        yield
    except click.ClickException:
        raise
    except expected as exc:
        if os.environ.get(DEBUG_ENV):
            raise
        raise click.ClickException(with_option(first_line(exc))) from None


def with_option(line: str) -> str:
    """Put the option in front of a message about one of its files ("PATH: ..." becomes
    "--run PATH: ..."): the libraries below the command line know the path, not the option."""
    import click

    ctx = click.get_current_context(silent=True)
    if ctx is None or line.startswith("-"):
        return line
    for param in ctx.command.params:
        name = next((o for o in param.opts if o.startswith("--")), None) if isinstance(param, click.Option) else None
        if name is None:
            continue
        values = ctx.params.get(param.name)
        for value in values if isinstance(values, (tuple, list)) else (values,):
            if isinstance(value, (str, os.PathLike)) and str(value) and line.startswith(f"{value}:"):
                return f"{name} {line}"
    return line
