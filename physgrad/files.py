"""Files written safely and text read safely: folder locks, writes renamed into place, plain YAML,
printable text.

Every writer of physgrad writes beside its target and renames onto it, so a reader or a process
killed at any instant sees the old file or the new one, never a part. Every text from a file
physgrad did not write is data: it is cleaned of control characters before it is printed and parsed
as plain YAML without aliases or tags.
"""

from __future__ import annotations

import errno
import fcntl
import os
import re
import socket
import stat
import time
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import datetime
from pathlib import Path
from typing import IO, Any

import yaml

from physgrad.errors import FolderOwned, LockingUnsupported


def owner_tag() -> str:
    return f"pid {os.getpid()} on {socket.gethostname()}"


# what "locks unsupported" looks like
NO_LOCKS = {errno.ENOLCK, errno.ENOSYS, errno.EOPNOTSUPP, errno.EINVAL}
HELD = {errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES}  # what "another process holds it" looks like


def _lock(fd: int, lock_path: Path) -> bool:
    """An exclusive, non-blocking lock on fd: flock, else (where the file system has no flock) a
    POSIX lock. True if taken, False if another process holds it; LockingUnsupported where neither
    kind works."""
    reasons = []
    for take in (fcntl.flock, fcntl.lockf):
        try:
            take(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except OSError as error:
            if error.errno in HELD:
                return False
            if error.errno not in NO_LOCKS:
                raise
            reasons.append(error.strerror or str(error))
    raise LockingUnsupported(
        f"cannot lock {lock_path}: the file system supports no file locks (flock: {reasons[0]}; "
        f"POSIX locks: {reasons[1]}): write to a local disk (e.g. hydra.sweep.dir=/tmp/...) or "
        "mount it with locking (Lustre: -o flock)"
    )


def lock_holder(stat: os.stat_result) -> int | None:
    """The pid of another process holding a lock on the file `stat` describes, as the kernel lists
    it (/proc/locks, Linux: flock and POSIX locks); None where that cannot be told."""
    try:
        lines = Path("/proc/locks").read_text().splitlines()
    except OSError:
        return None
    device = f"{os.major(stat.st_dev):02x}:{os.minor(stat.st_dev):02x}:{stat.st_ino}"
    for line in lines:
        fields = line.split()
        if "->" in fields or len(fields) < 6:  # a process waiting for the lock, not holding it
            continue
        if fields[5] == device and fields[4].isdigit() and int(fields[4]) != os.getpid():
            return int(fields[4])
    return None


@contextmanager
def own_folder(folder: str | os.PathLike, what: str = "job") -> Iterator[None]:
    """Hold the folder for this process while the block runs: an exclusive lock on
    folder/.physgrad-<what> (flock, or a POSIX lock where the file system has no flock), which the
    operating system releases when the process ends however it ends, so a dead owner never blocks a
    new one. FolderOwned (one line naming the owner's pid, host and start time) if a live process
    holds it; LockingUnsupported (one line) where the file system has no locks; OSError if the
    folder cannot be written or open_foreign refuses the lock file (a link, a second name, not a
    file). The lock file must stay: a second process that finds it deleted creates its own (see
    docs/results.md)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    lock_path = folder / f".physgrad-{what}"
    while True:
        try:  # never through a link or a second name: the owner line below would overwrite it
            fd = open_foreign(lock_path, write=True)
        except ValueError as error:
            raise OSError(errno.EPERM, str(error)) from None
        try:
            taken = _lock(fd, lock_path)
        except BaseException:
            os.close(fd)
            raise
        if not taken:
            says = clean_text(os.pread(fd, 512, 0).decode(errors="replace").strip(), 300)
            holder = lock_holder(os.fstat(fd))
            os.close(fd)
            owner = says or "another process"
            if holder is not None and not says.startswith(f"pid {holder} "):
                # the file's text is anyone's to write: name the process the system says holds it
                owner = f"pid {holder} on this host (its lock file says: {says or 'nothing'})"
            raise FolderOwned(
                f"{folder} is being written by {owner} (another {what}): wait for it to end, stop "
                "it, or write somewhere else"
            )
        try:
            if os.path.samestat(os.stat(lock_path), os.fstat(fd)):
                break
        except FileNotFoundError:
            pass
        os.close(fd)  # the file was replaced between open and lock: lock the one that is there now
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{owner_tag()} since {timestamp()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)  # releases the lock; the file stays (removing it would race with a new owner)


def cache_dir() -> Path:
    """The user's physgrad cache (generated datasets, compiled executables): $PHYSGRAD_CACHE, else
    $XDG_CACHE_HOME/physgrad, else ~/.cache/physgrad."""
    if os.environ.get("PHYSGRAD_CACHE"):
        return Path(os.environ["PHYSGRAD_CACHE"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "physgrad"


def open_foreign(path: Path, write: bool = False, follow: bool = False) -> int:
    """The one way physgrad opens a file in a folder that may come from someone else: a descriptor
    of the regular file at path, opened without following a link (unless follow: a path the user
    gave) and without waiting on a FIFO; write: for appending, created if absent, and refused if
    the file has another name (a hard link), which writing would change too. ValueError (one
    line) for a link, a FIFO, a device, a folder or a second name; OSError where it cannot be
    opened."""
    flags = os.O_NONBLOCK | os.O_NOCTTY | (0 if follow else os.O_NOFOLLOW)
    flags |= os.O_RDWR | os.O_APPEND | os.O_CREAT if write else os.O_RDONLY
    try:
        fd = os.open(path, flags, 0o644)
    except OSError as error:
        if error.errno in (errno.ELOOP, errno.EISDIR):
            why = "a link" if error.errno == errno.ELOOP else "a folder, not a file"
            why += ": refused (a folder may come from someone else)"
            raise ValueError(f"{path}: {why}") from None
        raise
    found = os.fstat(fd)
    why = (
        f"{file_kind(found.st_mode)}, not a file: refused"
        if not stat.S_ISREG(found.st_mode)
        else "has another name (a hard link), which writing would change too"
        if write and found.st_nlink > 1
        else None
    )
    if why:
        os.close(fd)
        raise ValueError(f"{path}: {why}")
    os.set_blocking(fd, True)
    return fd


def open_append(path: Path) -> IO[str]:
    """path opened for appending text through open_foreign (write)."""
    return os.fdopen(open_foreign(path, write=True), "a")


def read_own_file(path: Path, limit: int, follow: bool = False, tail: bool = False) -> bytes:
    """The regular file at path, opened through open_foreign; ValueError (one line) if it is longer
    than limit bytes (tail: its last limit bytes instead); OSError where it cannot be read."""
    with os.fdopen(open_foreign(path, follow=follow), "rb") as file:
        size = os.fstat(file.fileno()).st_size
        if tail:
            file.seek(max(0, size - limit))
        data = file.read(limit + 1)
    if len(data) > limit and not tail:
        raise ValueError(f"{path}: longer than {limit} bytes: not a file physgrad wrote")
    return data[:limit]


def walk_files(top: Path, name: str) -> Iterator[Path]:
    """Every entry called name under top (whatever it is: a link, a FIFO...; the reader refuses what
    is not a regular file), the folders walked with an explicit stack, never through a link (a
    folder from someone else could point one at / or at itself) and without recursion however deep
    they go; a folder that cannot be read or vanishes holds nothing."""
    stack = [top]
    while stack:
        try:
            entries = list(os.scandir(stack.pop()))
        except OSError:
            continue
        for entry in entries:
            folder = entry.is_dir(follow_symlinks=False)
            if entry.name == name and not folder:
                yield Path(entry.path)
            elif folder:
                stack.append(Path(entry.path))


def inside(path: Path, folder: Path) -> bool:
    """Whether path is folder or lies under it, links resolved (a link loop is not resolved, and
    is not inside)."""
    return Path(os.path.realpath(path)).is_relative_to(os.path.realpath(folder))


def load_json(data: bytes) -> object:
    """JSON text as data; ValueError (one line) for text that is not JSON or nests deeper than the
    parser's recursion allows (a crafted file of 200,000 brackets)."""
    import json

    try:
        return json.loads(data.decode())
    except RecursionError:
        raise ValueError("nested too deep to be a physgrad file") from None


@contextmanager
def replaced(path: Path, text: bool = False, sync: bool = False) -> Iterator[IO]:
    """The one way physgrad writes a file into a folder (a study's, a sweep's, a job's: folders that
    may come from someone else): a file object on .NAME.<pid>.tmp beside path, renamed onto path
    when the block ends without error (else removed), so that a reader, or a process killed at any
    instant, sees the old file or the new one, never a part (sync: onto the disk itself before the
    rename, which a power cut could otherwise undo). A link at path is replaced, never written
    through; the temporary file is created exclusively and without following a link (one left by a
    process killed before, or a link planted at its name, is removed first). text: a text file
    (no newline translation), else bytes."""
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    temporary.unlink(missing_ok=True)
    try:
        flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
        fd = os.open(temporary, flags, 0o666)
        with os.fdopen(fd, "w", newline="") if text else os.fdopen(fd, "wb") as out:
            yield out
            if sync:
                out.flush()
                os.fsync(out.fileno())
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def make_folder(path: str | os.PathLike, levels: int = 1) -> Path:
    """The one way physgrad makes a folder inside a folder that may come from someone else (a
    study's report/, a run's seed=N/, a job's .hydra/, a sweep's job records): created with its
    parents, and refused (LinkedFolder, an OSError: one line) where the folder or any of its
    `levels` - 1 parents below is a link or not a folder, so that nothing is written through a
    link planted at the name physgrad would create (mkdir on a link to a folder succeeds)."""
    path = Path(path)
    chain = [path, *path.parents][:levels]
    for part in reversed(chain):
        try:
            mode = os.lstat(part).st_mode
        except FileNotFoundError:
            part.mkdir(parents=True, exist_ok=True)
            mode = os.lstat(part).st_mode
        if not stat.S_ISDIR(mode):
            kind = "a link" if stat.S_ISLNK(mode) else "a file" if stat.S_ISREG(mode) else None
            raise LinkedFolder(
                f"{part} is {kind or file_kind(mode)}, not a folder: physgrad writes through no "
                "link or file planted at a name it creates; remove it and run again"
            )
    return path


class LinkedFolder(OSError):
    """A folder physgrad would create is a link or a file (make_folder)."""


def replace_file(path: Path, content: bytes, sync: bool = False) -> None:
    """content written into path through `replaced`."""
    with replaced(path, sync=sync) as out:
        out.write(content)


def write_text(path: str | os.PathLike, text: str) -> None:
    """text written into path through `replaced` (the write door: a link at path is replaced,
    never written through)."""
    replace_file(Path(path), text.encode())


def write_figure(fig: Any, path: str | os.PathLike, **options: Any) -> None:
    """A matplotlib figure saved to path (the format from its suffix), written beside and renamed
    (replace_file): a reader sees the old figure or the new one, and a link at path (a folder that
    may come from someone else) is replaced, not written through. A PDF carries no creation date,
    so the same figure gives the same bytes (a committed figure regenerates byte for byte)."""
    import io

    path = Path(path)
    buffer = io.BytesIO()
    kind = path.suffix.lstrip(".") or "png"
    if kind == "pdf":
        options = {"metadata": {"CreationDate": None, **options.pop("metadata", {})}, **options}
    fig.savefig(buffer, format=kind, **options)
    replace_file(path, buffer.getvalue())


def timestamp() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


TEXT_LIMIT = 2000  # characters of one text attribute (config excepted): longer text is cut
CONFIG_LIMIT = 1 << 20  # bytes of the stored config; a physgrad config is a few kB


# C0/C1 controls, bidi overrides
_UNSAFE = re.compile("[\x00-\x08\x0b-\x1f\x7f-\x9f\u202a-\u202e\u2066-\u2069]")


def safe_name(text: str, limit: int = 40) -> str:
    """text as a part of a file name and of a console line: letters, digits, '.', '_' and '-'
    kept, anything else (a control character, a path separator) replaced by '_', cut to limit."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", text)[:limit] or "_"


def clean_text(text: str, limit: int | None = TEXT_LIMIT, lines: bool = False) -> str:
    """text safe to print: control characters (an ANSI escape's ESC among them) and bidirectional
    overrides replaced by U+FFFD, newlines and tabs too unless lines, cut to limit characters."""
    text = _UNSAFE.sub("\ufffd", text if lines else text.replace("\n", " ").replace("\t", " "))
    return text if limit is None or len(text) <= limit else text[:limit] + "... (cut)"


# libyaml's parser where PyYAML was built with it (its wheels are): about eight times faster than
# PyYAML's own, which a study's resume or a report pays for every results file's stored config
_Loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


# a physgrad config nests a few levels (hydra's section about 6); deeper is no config of physgrad's,
# and 500 levels made every later reader (OmegaConf, report) fail with a RecursionError
MAX_DEPTH = 64


def _without_aliases(root: yaml.Node | None) -> None:
    """YAMLError if a node of the composed document is reached twice: an alias (*name), which a
    few bytes of nested ones expand to gigabytes (a 'billion laughs'), and physgrad never writes;
    or if it nests deeper than MAX_DEPTH. The composer hands back the anchored node itself for an
    alias, so identity finds every one."""
    seen: set[int] = set()
    todo = [] if root is None else [(root, 1)]
    while todo:
        node, depth = todo.pop()
        if id(node) in seen:
            raise yaml.YAMLError("aliases (*name) are not allowed")
        if depth > MAX_DEPTH:
            raise yaml.YAMLError(f"nested deeper than {MAX_DEPTH} levels")
        seen.add(id(node))
        if isinstance(node, yaml.MappingNode):
            todo.extend((item, depth + 1) for pair in node.value for item in pair)
        elif isinstance(node, yaml.SequenceNode):
            todo.extend((item, depth + 1) for item in node.value)


def load_yaml(text: str) -> Any:
    """Plain YAML data (no aliases, no tags beyond YAML's own); ValueError (one line) if it is not
    that."""
    loader = _Loader(text)
    try:
        root = loader.get_single_node()
        _without_aliases(root)
        return None if root is None else loader.construct_document(root)
    except (yaml.YAMLError, RecursionError, ValueError) as error:
        raise ValueError(
            f"not plain YAML ({clean_text(str(error).splitlines()[0], 200)})"
        ) from None
    finally:
        loader.dispose()


def read_small_yaml(path: Path, limit: int = CONFIG_LIMIT) -> Any:
    """load_yaml of a file read through read_own_file (a sweep's jobs.yaml, overrides.yaml,
    Optuna's optimization_results.yaml: other people's folders too); ValueError (one line)
    otherwise."""
    text = read_own_file(path, limit).decode(errors="replace")  # its errors name the path
    try:
        return load_yaml(text)
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None


def file_kind(mode: int) -> str:
    kinds = {"p": "a FIFO", "c": "a character device", "b": "a block device", "s": "a socket"}
    return {**kinds, "d": "a folder"}.get(stat.filemode(mode)[0], "not a plain file")


# A writer's liveness: the `owner` (pid N on HOST) and `heartbeat` (its latest write) it records.
def owner_alive(owner: str) -> bool | None:
    """Whether the process named by an `owner` attribute (pid N on HOST) still runs: None when that
    cannot be told from here (another host, or a file without an owner)."""
    match = re.fullmatch(r"pid (\d+) on (.+)", owner or "")
    if match is None or match[2] != socket.gethostname():
        return None
    try:
        os.kill(int(match[1]), 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


STALE_SECONDS = 3600  # a writer on another host that wrote nothing for this long is taken for dead


def with_live_status(attrs: dict, now: float | None = None) -> dict:
    """A file that says `running` whose writer is gone reads as `crashed` (killed, or its machine
    lost), with a reason; the file itself is left as it is. A writer on another host cannot be
    asked: it counts as gone when its heartbeat (the time of its latest write) is more than
    STALE_SECONDS old."""
    if attrs.get("status") != "running":
        return attrs
    alive = owner_alive(attrs.get("owner", ""))
    if alive is None:
        age = heartbeat_age(attrs.get("heartbeat", ""), now)
        alive = None if age is None else age <= STALE_SECONDS
        owner = attrs.get("owner", "?")
        why = f"its writer ({owner}, on another host) has not written for {age or 0:.0f} s"
    else:
        why = f"its writer ({attrs['owner']}) ended without finishing"
    if alive is False:
        attrs["status"] = "crashed"
        attrs["reason"] = (
            f"{why}; rows up to its last write ({attrs.get('heartbeat', '?')}) are kept"
        )
    return attrs


def heartbeat_age(heartbeat: str, now: float | None = None) -> float | None:
    """Seconds since an ISO heartbeat with its UTC offset (None if it is not one)."""
    try:
        stamp = datetime.strptime(heartbeat, "%Y-%m-%dT%H:%M:%S%z").timestamp()
    except (ValueError, TypeError, OverflowError):
        return None
    return (time.time() if now is None else now) - stamp
