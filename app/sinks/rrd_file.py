"""The .rrd file behind a Rerun recording stream, written by a thread of lightflow's own.

Why not the SDK's own file writer: in rerun-sdk 0.41 that writer is a thread which
ends when a write fails (a full disk, a file size limit).  A ``flush`` that races
with its end waits forever, and so do ``disconnect`` and the SDK's exit hook: the
run hangs instead of stopping with an error (about 1 run in 10 under load).  So the
SDK writes into a pipe, whose writes never fail while it is drained, and
:class:`RrdFile` copies the pipe into the file.  A failed write is kept as
:attr:`RrdFile.error` and the pipe is drained to its end all the same, so the SDK
never notices.
"""

from __future__ import annotations

import errno
import fcntl
import os
import threading
from pathlib import Path

#: bytes per read from the pipe; the pipe is enlarged to this where the system allows
CHUNK_BYTES = 1 << 20
#: how long :meth:`RrdFile.finish` waits for the copy to end after the SDK let go, s
FINISH_TIMEOUT_S = 30.0


class RrdFile:
    """Copy a Rerun byte stream from a pipe into ``path`` on a thread.

    Parameters
    ----------
    path : Path
        The .rrd to write (created or truncated now; an OSError is the caller's).

    Attributes
    ----------
    error : OSError or None
        The first failed write; what followed it was read and dropped.

    Notes
    -----
    Hand :attr:`sink_path` to ``RecordingStream.save`` or ``rerun.FileSink``; call
    :meth:`finish` after the stream's ``disconnect``.  Linux only (``/proc/self/fd``).
    """

    def __init__(self, path: Path):
        self.path = Path(path)
        self.error: OSError | None = None
        self._file = open(self.path, "wb")  # noqa: SIM115 - closed by the copy thread
        self._read_fd, self._write_fd = os.pipe()
        try:
            fcntl.fcntl(self._write_fd, fcntl.F_SETPIPE_SZ, CHUNK_BYTES)
        except OSError:
            pass  # above the system's pipe-max-size: the default pipe works, in smaller reads
        self._thread = threading.Thread(target=self._copy, name="rrd-file", daemon=True)
        self._thread.start()

    @property
    def sink_path(self) -> str:
        """The path the SDK opens: a second write end of the pipe."""
        return f"/proc/self/fd/{self._write_fd}"

    def _copy(self) -> None:
        file = self._file
        try:
            while chunk := os.read(self._read_fd, CHUNK_BYTES):
                if file is None:
                    continue  # after a failure: drain, so the SDK's writes never block
                try:
                    file.write(chunk)
                except OSError as exc:
                    self.error = exc
                    self._close_quietly(file)
                    file = None
            if file is not None:
                try:
                    file.close()  # flushes the last buffered bytes, which may fail too
                except OSError as exc:
                    self.error = exc
                    self._close_quietly(file)
        finally:
            os.close(self._read_fd)

    @staticmethod
    def _close_quietly(file) -> None:
        try:
            file.close()
        except OSError:
            pass  # the first error is the one reported

    def finish(self) -> None:
        """Close lightflow's write end and wait until everything is in the file.

        Call after the SDK closed its own end (``disconnect``).  A copy still running
        after :data:`FINISH_TIMEOUT_S` becomes :attr:`error`.
        """
        if self._write_fd >= 0:
            os.close(self._write_fd)
            self._write_fd = -1
        self._thread.join(FINISH_TIMEOUT_S)
        if self._thread.is_alive() and self.error is None:
            self.error = TimeoutError(errno.ETIMEDOUT, "the Rerun SDK did not close its stream")

    def reason(self) -> str:
        """Why the file could not be written, in a few words (``error`` must be set)."""
        exc = self.error
        code = getattr(exc, "errno", None)
        if code in (errno.ENOSPC, errno.EDQUOT):
            return "the disk is full"
        if code == errno.EFBIG:
            return "the file size limit was reached"
        return (getattr(exc, "strerror", None) or str(exc)).lower()
