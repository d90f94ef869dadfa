"""Writing files safely: compact JSON, and outputs written under temporary names and renamed into place.

`atomic_paths` hands out temporary files beside their targets and renames them into place only when
every one was written (`os.replace`, which never follows a symlink at the destination), so a failed run
leaves the previous outputs as they were and no partial file.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import tempfile
from pathlib import Path
from typing import Any

import numpy as np


def jsonable(v) -> Any:
    if isinstance(v, dict):
        return {str(k): jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [jsonable(x) for x in v]
    if isinstance(v, (np.generic, np.ndarray)) or hasattr(v, "__array__"):
        a = np.asarray(v)
        return jsonable(a.tolist()) if a.ndim else jsonable(a.item())
    if isinstance(v, float) and not np.isfinite(v):
        return None
    if isinstance(v, Path):
        return str(v)
    return v


_NUMBERS = r"-?[0-9][0-9.eE+-]*|null|true|false"

_FLAT_LIST = re.compile(rf"\[\s*((?:{_NUMBERS})(?:,\s*(?:{_NUMBERS}))*)\s*\]")

_NESTED_LIST = re.compile(r"\[\s*(\[[^\[\]\n]*\](?:,\s*\[[^\[\]\n]*\])*)\s*\]")


def dumps(doc) -> str:
    """JSON text, indented, with short lists of numbers (sizes, 3 x 3 rotations) kept on one line."""
    doc = jsonable(doc)
    plain = json.dumps(doc, indent=2, allow_nan=False)
    text = _FLAT_LIST.sub(lambda m: "[" + ", ".join(v.strip() for v in m.group(1).split(",")) + "]", plain)
    text = _NESTED_LIST.sub(lambda m: "[" + ", ".join(re.findall(r"\[[^\[\]]*\]", m.group(1))) + "]", text)
    return text if json.loads(text) == doc else plain  # a string that looked like a list: keep it as it was


def write_json(doc: dict, path) -> Path:
    """Write `doc` as JSON (`dumps`) to `path`, atomically (`atomic_paths`); returns the path."""
    path = Path(os.fspath(path))
    text = dumps(doc) + "\n"
    with atomic_paths(path) as (tmp,):
        tmp.write_text(text)
    return path


def write_error(path, e: OSError) -> OSError:
    """An OSError whose message names `path` (the caller's target, not a temporary)."""
    return (
        OSError(e.errno, f"{path}: cannot write ({e.strerror or type(e).__name__})")
        if e.errno
        else OSError(f"{path}: cannot write ({e})")
    )


def check_writable_dir(path) -> Path:
    """Create folder `path` if needed and prove it writable by creating (and removing) a temporary
    folder in it; raises OSError naming `path` otherwise. Call before long work."""
    path = Path(os.fspath(path))
    if os.path.lexists(path) and not path.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, f"{path}: exists and is not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
        os.rmdir(tempfile.mkdtemp(prefix=".sqjax-check-", dir=path))
    except OSError as e:
        raise write_error(path, e) from None
    return path


def check_writable_file(path) -> Path:
    """Prove that file `path` can be written (its folder exists and takes a new file; `path` is not a
    folder), without touching `path` itself; raises OSError naming `path`."""
    path = Path(os.fspath(path))
    if path.is_dir():
        raise IsADirectoryError(errno.EISDIR, f"{path}: is a folder, expected a file name")
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise FileNotFoundError(errno.ENOENT, f"{path}: folder {parent} does not exist")
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".check", dir=parent)
        os.close(fd)
        os.unlink(tmp)
    except OSError as e:
        raise write_error(path, e) from None
    return path


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_paths(*paths):
    """Yield one temporary path per target (same folder, same extension, created exclusively); on
    success each is renamed onto its target with `os.replace` (a symlink at the target is replaced,
    never followed), on failure all are removed and no target is touched."""
    targets = [Path(os.fspath(p)) for p in paths]
    tmps = []
    try:
        for t in targets:
            if t.is_dir() and not t.is_symlink():
                raise IsADirectoryError(errno.EISDIR, f"{t}: is a folder, expected a file name")
            try:
                fd, tmp = tempfile.mkstemp(
                    prefix=f".{t.name}.", suffix=t.suffix, dir=t.parent if str(t.parent) else "."
                )
            except OSError as e:
                raise write_error(t, e) from None
            os.close(fd)
            tmps.append(Path(tmp))
            os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; outputs get the usual permissions
        try:
            yield tuple(tmps)
        except OSError as e:
            bad = getattr(e, "filename", None)
            named = {str(tmp): t for tmp, t in zip(tmps, targets)}
            if bad is not None and str(bad) in named:
                raise write_error(named[str(bad)], e) from None
            raise
        for tmp, t in zip(tmps, targets):
            try:
                os.replace(tmp, t)
            except OSError as e:
                raise write_error(t, e) from None
    finally:
        for tmp in tmps:
            with contextlib.suppress(OSError):
                tmp.unlink()
