"""A full disk: recognising it behind the errors h5py and torch wrap it in, and the one-line
error that says how much room there is and how much the write wanted."""
from __future__ import annotations

import contextlib
import errno
import os
from pathlib import Path

from pipeline.errors import PipelineError


def disk_full(exc: BaseException | None) -> bool:
    """Whether an exception, or one it was raised from, is a full disk (h5py and torch wrap
    the OSError, or only say so in their message)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if getattr(exc, "errno", None) in (errno.ENOSPC, errno.EDQUOT) or "No space left on device" in str(exc):
            return True
        exc = exc.__cause__ or exc.__context__
    return False


def raise_if_full(exc: OSError, where: Path, need: int | None) -> None:
    """A write that failed for lack of space becomes the one-line 'store full' error."""
    if disk_full(exc):
        raise StoreFull(where, need) from None


class StoreFull(PipelineError):
    """The store's disk is full: one line, exit 2.  The free space is measured when the message
    is shown, after the writer deleted its temp file: what the user can count on."""

    def __init__(self, where: Path, need: int | None):
        super().__init__(where, need)
        self.where, self.need = Path(where), need

    def __str__(self) -> str:
        free, device = _free_space(self.where)
        wanted = f", need about {self.need}" if self.need else ""
        return f"store full: {free} bytes free on {device}{wanted}"


def _free_space(where: Path) -> tuple[int, str]:
    """(bytes free to this user, 'mountpoint (device)') of the filesystem holding `where`."""
    where = Path(where)
    while not where.exists() and where != where.parent:
        where = where.parent
    try:
        st = os.statvfs(where)
        free = st.f_bavail * st.f_frsize
    except OSError:
        free = 0
    device, mount, best = "?", str(where), -1
    with contextlib.suppress(OSError):
        real = os.path.realpath(where)
        for line in Path("/proc/mounts").read_text().splitlines():
            parts = line.split()
            if len(parts) < 2:
                continue
            point = parts[1].replace("\\040", " ")
            inside = real == point or real.startswith(point.rstrip("/") + "/")
            if inside and len(point) > best:
                device, mount, best = parts[0], point, len(point)
    return free, f"{mount} ({device})" if device != "?" else mount
