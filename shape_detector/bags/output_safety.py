"""Output-path safety for tools that read one bag and write another.

* :func:`check_output_path`: the output must not be, lie inside, or contain the input
  (paths resolved, symlinks followed), so ``--overwrite`` can never delete the input.
* :class:`PartialOutput`: the output is written under a sibling temporary name
  (``.OUT.partial-<pid>``) and renamed into place only once it is complete; an old
  output is replaced only then.
* :class:`StopSignals`: SIGINT / SIGTERM set a flag the writer checks between messages,
  so the output can be finalised with the frames written so far.
"""

from __future__ import annotations

import errno
import os
import shutil
import signal
from pathlib import Path
from types import FrameType
from typing import Any, Literal

#: exit status of a run stopped by a signal: 128 + the signal number (shell convention)
EXIT_SIGINT = 128 + int(signal.SIGINT)
EXIT_SIGTERM = 128 + int(signal.SIGTERM)


class OutputError(OSError):
    """The output bag at ``path`` could not be written; ``str()`` is one line."""

    def __init__(self, path: Path | str, cause: OSError) -> None:
        super().__init__(cause.errno, cause.strerror or str(cause))
        self.path = str(path)
        self.cause = cause

    def __str__(self) -> str:
        where = f" ({self.cause.filename})" if self.cause.filename and str(self.cause.filename) != self.path else ""
        return f"cannot write output {self.path!r}{where}: {self.strerror or self.cause}"


class UnsafeOutputError(ValueError):
    """The output path would overwrite or delete (part of) the input."""


def _resolved(p: Path | str) -> Path:
    return Path(os.path.abspath(p)).resolve(strict=False)


def _within(child: Path, parent: Path) -> bool:
    return child == parent or parent in child.parents


def check_output_path(in_path: Path | str, out_path: Path | str) -> None:
    """Raise :class:`UnsafeOutputError` when ``out_path`` is ``in_path``, lies inside
    it, or contains it (a bag directory holds the input file too)."""
    src, dst = _resolved(in_path), _resolved(out_path)
    inputs = [src]
    if src.is_file() and (src.parent / "metadata.yaml").exists():
        inputs.append(src.parent)  # a .mcap given directly: its bag directory is the input too
    for inp in inputs:
        if dst == inp:
            raise UnsafeOutputError(f"output {str(out_path)!r} is the input bag {str(in_path)!r}")
        if _within(dst, inp):
            raise UnsafeOutputError(f"output {str(out_path)!r} lies inside the input bag {str(in_path)!r}")
        if _within(inp, dst):
            raise UnsafeOutputError(f"output {str(out_path)!r} contains the input bag {str(in_path)!r}")
    if dst.exists() and src.exists() and os.path.samefile(dst, src):  # hard links, bind mounts
        raise UnsafeOutputError(f"output {str(out_path)!r} is the input bag {str(in_path)!r}")


def check_replaceable(out_path: Path) -> None:
    """Raise FileExistsError unless an existing ``out_path`` looks like a bag this tool
    may replace: a directory with ``metadata.yaml`` or ``.mcap`` files, an empty
    directory, or a ``.mcap`` file."""
    if out_path.is_dir():
        if (out_path / "metadata.yaml").exists() or any(out_path.glob("*.mcap")) or not any(out_path.iterdir()):
            return
        raise FileExistsError(f"output {str(out_path)!r} is a non-empty directory that is not a bag; not replacing it")
    if out_path.suffix != ".mcap":
        raise FileExistsError(f"output {str(out_path)!r} is a file that is not a bag; not replacing it")


class PartialOutput:
    """An output bag directory written under a temporary sibling name.

    ``tmp``: where to write (does not exist yet; its parent does after
    :meth:`prepare`). :meth:`commit` renames it to ``final`` (replacing an old output
    only when ``overwrite``); :meth:`discard` removes it."""

    def __init__(self, final: Path | str, overwrite: bool = False) -> None:
        self.final = Path(final)
        self.overwrite = overwrite
        self.tmp = self.final.parent / f".{self.final.name}.partial-{os.getpid()}"
        self._old = self.final.parent / f".{self.final.name}.old-{os.getpid()}"

    def check(self) -> None:
        """Check the destination without changing anything: FileExistsError for an
        output that exists (without ``overwrite``) or is not a bag; OutputError when a
        parent is a file or the nearest existing parent is not writable."""
        if os.path.lexists(self.final):
            if not self.overwrite:
                raise FileExistsError(f"output {str(self.final)!r} exists (use --overwrite)")
            check_replaceable(self.final)
        parent = self.final.absolute().parent
        while not os.path.lexists(parent) and parent != parent.parent:
            parent = parent.parent
        if not parent.is_dir():
            cause = NotADirectoryError(errno.ENOTDIR, "a parent is a file, not a directory", str(parent))
            raise OutputError(self.final, cause)
        if not os.access(parent, os.W_OK | os.X_OK):
            raise OutputError(self.final, PermissionError(errno.EACCES, "permission denied", str(parent)))

    def prepare(self) -> None:
        """:meth:`check`, then create the parent (OutputError when impossible)."""
        self.check()
        try:
            self.final.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise OutputError(self.final, e) from e
        if os.path.lexists(self.tmp):
            _remove(self.tmp)

    def commit(self) -> None:
        """Move the finished bag into place; the old output goes only after that."""
        if os.path.lexists(self.final):
            if not self.overwrite:
                raise FileExistsError(f"output {str(self.final)!r} appeared while writing (use --overwrite)")
            if os.path.lexists(self._old):
                _remove(self._old)
            os.replace(self.final, self._old)
            try:
                os.replace(self.tmp, self.final)
            except OSError:
                os.replace(self._old, self.final)
                raise
            _remove(self._old)
        else:
            os.replace(self.tmp, self.final)

    def discard(self) -> None:
        """Remove the temporary output (after a failure); never touches ``final``."""
        if os.path.lexists(self.tmp):
            _remove(self.tmp)


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        try:
            p.unlink()
        except OSError:
            pass


class StopSignals:
    """Context manager: SIGINT and SIGTERM (main thread only) set :attr:`signum`
    instead of stopping the process; a second signal raises KeyboardInterrupt at once.
    The previous handlers come back on exit."""

    def __init__(self, signals: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> None:
        self.signals = signals
        self.signum: int | None = None
        self._old: dict[int, Any] = {}

    def _handler(self, signum: int, frame: FrameType | None) -> None:
        if self.signum is not None:
            raise KeyboardInterrupt
        self.signum = signum

    @property
    def name(self) -> str | None:
        """``'SIGINT'`` / ``'SIGTERM'`` once a signal arrived, else None."""
        return None if self.signum is None else signal.Signals(self.signum).name

    def __call__(self) -> str | None:
        """The received signal's name, or None (a ``should_stop`` callable)."""
        return self.name

    def __enter__(self) -> StopSignals:
        import threading

        if threading.current_thread() is threading.main_thread():
            for s in self.signals:
                self._old[s] = signal.signal(s, self._handler)
        return self

    def __exit__(self, *exc: Any) -> None:
        for s, old in self._old.items():
            signal.signal(s, old)
        self._old.clear()


class SafeOutputBag:
    """Context manager around :class:`~shape_detector.bags.output.OutputBag` for a tool
    that reads ``in_path`` and writes the bag ``out_path``.

    Checks the paths (:func:`check_output_path`), writes under a temporary sibling name,
    and on a normal exit (including a handled stop) finalises the bag and renames it
    into place; when an exception escapes, the partial output is removed instead and the
    exception goes on. The input is never touched."""

    def __init__(self, in_path: Path | str, out_path: Path | str, *, overwrite: bool = False,
                 write_detections: bool = True) -> None:
        check_output_path(in_path, out_path)
        self.partial = PartialOutput(out_path, overwrite)
        self.write_detections = write_detections
        self.bag: Any = None

    def __enter__(self) -> Any:
        from .output import OutputBag

        final = self.partial.final
        self.partial.prepare()
        try:
            self.bag = OutputBag(self.partial.tmp, write_detections=self.write_detections,
                                 file_name=final.name, report_path=final)
        except BaseException:
            self.partial.discard()
            raise
        return self.bag

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> Literal[False]:
        if exc is not None:
            self.bag.abort()
            self.partial.discard()
            return False
        try:
            self.bag.close()
            self.partial.commit()
        except OSError as e:
            self.bag.abort()
            self.partial.discard()
            if isinstance(e, OutputError):
                raise
            raise OutputError(self.partial.final, e) from e
        return False
