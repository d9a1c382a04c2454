"""An output directory written as one atomic set.

The whole set is written into a staging directory beside the target (``.groom-tmp-<name>-<pid>-<id>.new``),
then swapped in: on Linux by one ``renameat2(RENAME_EXCHANGE)`` (the target is the old complete set,
then the new one, never a mix), elsewhere by renaming the old directory aside (``...old``) and the new
one in.  An interrupt at any moment leaves the old complete set or the new complete set at the target
(in the fallback's instant between the two renames, the old set waits beside it and the next
``recover`` puts it back).  Leftover ``.groom-tmp-*`` directories of dead processes are removed by the
next write.

Files of the old directory that are not outputs of a run (``OWNED`` names) are carried into the new set
by hard links (copies where links fail), so only stale outputs of an earlier run disappear; a
directory inside the old one is refused (GroomError) rather than copied or deleted.
"""

from __future__ import annotations

import ctypes
import os
import shutil
import sys
import uuid
from contextlib import contextmanager
from pathlib import Path

from ..groom import GroomError

PREFIX = ".groom-tmp-"
# Files an inversion run writes or derives from its rest.npz: replaced or dropped as a set.
OWNED = frozenset({
    "rest.npz", "rest_shape.obj", "fitted.obj", "report.json", "check.json", "groom.usdc", "groom.usda", "groom.usd",
    "groom.abc", "groom.vtp", "groom_head.vtp", "rest_shape.hair", "fitted.hair",
})
_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _renameat2():
    if not sys.platform.startswith("linux"):
        return None
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    fn.restype = ctypes.c_int
    return fn


_RENAMEAT2 = _renameat2()


def exchange(a: Path, b: Path) -> bool:
    """Atomically swap two existing paths; False where the system cannot (then nothing changed)."""
    if _RENAMEAT2 is None:
        return False
    if _RENAMEAT2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (22, 38, 95):  # EINVAL, ENOSYS, EOPNOTSUPP: file system or kernel without it
        return False
    raise OSError(err, os.strerror(err), str(b))


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _leftovers(target: Path) -> list[Path]:
    """Staging and set-aside directories of earlier runs on ``target`` whose process has ended."""
    out = []
    if not target.parent.is_dir():
        return out
    head = f"{PREFIX}{target.name}-"
    for p in target.parent.iterdir():
        if not p.name.startswith(head) or not p.name.endswith((".new", ".old")):
            continue
        pid = p.name[len(head):].split("-", 1)[0]
        if pid.isdigit() and int(pid) != os.getpid() and _pid_alive(int(pid)):
            continue  # another run is writing it now
        out.append(p)
    return out


def recover(target) -> None:
    """Tidy ``target``'s leftovers: put a set-aside old set back if the target is missing (a run
    killed between its two renames), remove the rest.  Safe to call any time; readers may call it."""
    target = Path(target)
    leftovers = _leftovers(target)
    if not target.exists():
        old = sorted((p for p in leftovers if p.name.endswith(".old")), key=lambda p: p.stat().st_mtime)
        if old:
            os.rename(old[-1], target)
            leftovers.remove(old[-1])
    for p in leftovers:
        shutil.rmtree(p, ignore_errors=True)


def _link_or_copy(src, dst):
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)
    return dst


def _check_foreign(target: Path, outdir) -> None:
    """A directory inside the target is refused: the set is replaced as a whole, and a directory
    (maybe a mount point, maybe large) is not something to copy or delete on the user's behalf.
    So is the current directory or one holding it (the shell would be left in a removed one)."""
    if not target.is_dir():
        return
    cwd = Path.cwd().resolve()
    if target.resolve() == cwd or target.resolve() in cwd.parents:
        raise GroomError(f"{outdir}: is (or holds) the current directory, which the output set would replace: "
                         "give a directory of its own (e.g. -o out)")
    for p in target.iterdir():
        if p.name not in OWNED and p.is_dir() and not p.is_symlink():
            raise GroomError(
                f"{outdir}: holds the directory {p.name!r}, which is not an output of groom invert: give the "
                "outputs a directory of their own (the output set is replaced as a whole)")


def _carry_unowned(old: Path, new: Path) -> None:
    """Hard-link the files the old directory holds besides run outputs into the new set."""
    for p in old.iterdir():
        if p.name in OWNED or (new / p.name).exists():
            continue
        if p.is_symlink():
            os.symlink(os.readlink(p), new / p.name)
        elif p.is_file():
            _link_or_copy(p, new / p.name)


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _fsync_tree(path: Path) -> None:
    for p in path.iterdir():
        if p.is_file() and not p.is_symlink():
            fd = os.open(p, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
    _fsync_dir(path)


def resolve_target(outdir) -> Path:
    """The output directory as an absolute path, a symlink to a directory followed."""
    outdir = Path(outdir).absolute()
    return outdir.resolve() if outdir.is_symlink() else outdir


def check_target(outdir, inputs=()) -> Path:
    """Check before any computation that ``outdir`` can take an output set; returns it resolved.

    GroomError when it is a file, when its nearest existing ancestor is not a writable directory,
    or when one of ``inputs`` (the groom, the head) is a file the set would replace or drop.
    """
    target = resolve_target(outdir)
    if target.exists() and not target.is_dir():
        raise GroomError(f"{outdir}: exists and is not a directory: give a directory for the outputs")
    ancestor = target.parent
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise GroomError(f"{outdir}: cannot create it: {ancestor} is a file, not a directory")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise GroomError(f"{outdir}: cannot write there: {ancestor} is not writable")
    _check_foreign(target, outdir)
    probe = ancestor / f"{PREFIX}probe-{os.getpid()}-{uuid.uuid4().hex[:8]}.new"
    try:
        probe.mkdir()
        probe.rmdir()
    except OSError as exc:
        raise GroomError(f"{outdir}: cannot write there: {exc.strerror or exc}") from None
    for path in inputs:
        if path is None:
            continue
        p = Path(path).absolute()
        if p.parent.resolve() == target and p.name in OWNED:
            raise GroomError(
                f"{path}: the input lies in the output directory {outdir} and would be replaced by the run's "
                f"{p.name}: choose another -o directory (or move the input)")
    return target


@contextmanager
def output_set(outdir):
    """Yield a fresh staging directory; on a clean exit it becomes ``outdir`` in one swap.

    If the body raises (or the process is interrupted) ``outdir`` is untouched and the staging
    directory is removed (or, after SIGKILL, left for the next ``recover``).
    """
    target = resolve_target(outdir)
    target.parent.mkdir(parents=True, exist_ok=True)
    recover(target)
    if target.exists() and not target.is_dir():
        raise GroomError(f"{outdir}: exists and is not a directory")
    _check_foreign(target, outdir)
    run = f"{PREFIX}{target.name}-{os.getpid()}-{uuid.uuid4().hex[:12]}"
    stage, aside = target.with_name(run + ".new"), target.with_name(run + ".old")
    stage.mkdir()
    try:
        yield stage
        if target.exists():
            _carry_unowned(target, stage)
        _fsync_tree(stage)
        commit(stage, target, aside)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        if not target.exists():  # interrupted between the fallback's two renames: old set back
            recover(target)
        raise


def commit(stage: Path, target: Path, aside: Path) -> None:
    """Swap the complete set ``stage`` in at ``target``; the old set (if any) is removed."""
    if not target.exists():
        os.rename(stage, target)
        _fsync_dir(target.parent)
        return
    if exchange(stage, target):  # stage now holds the old set
        _fsync_dir(target.parent)
        shutil.rmtree(stage, ignore_errors=True)
        return
    os.rename(target, aside)
    os.rename(stage, target)
    _fsync_dir(target.parent)
    shutil.rmtree(aside, ignore_errors=True)
