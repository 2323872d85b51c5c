"""Directories that rtsgt writes: assembled aside, put in place whole, replaced only if ours.

:class:`OutputDir` writes into a hidden temporary directory beside the target, renamed into
place at the end, with a manifest (``.rtsgt-output.json``) of every file rtsgt wrote; an
existing target is replaced only if empty or, with ``force``, an rtsgt output, never if it
holds the working directory or an input. :func:`open_output_folder` (filled over several
calls), :func:`complete_output`, :func:`record_files` (files added later) and
:func:`check_output_file` (single files) complete it. docs/cli.md.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
from collections.abc import Callable, Iterable
from pathlib import Path
from types import TracebackType

from rtsgt import __version__
from rtsgt.errors import InputError

#: Name of the manifest file in every directory rtsgt writes.
MANIFEST = ".rtsgt-output.json"


def _manifest(folder: Path) -> dict | None:
    """The manifest of ``folder`` as read, or None if it has no valid rtsgt manifest."""
    try:
        doc = json.loads((folder / MANIFEST).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or doc.get("written_by") != "rtsgt":
        return None
    files = doc.get("files")
    if not isinstance(files, list) or not all(isinstance(f, str) for f in files):
        return None
    return doc


def _listed_files(folder: Path) -> set[Path] | None:
    """Files listed by the manifest of ``folder`` (absolute), or None if it has no valid one."""
    doc = _manifest(folder)
    return None if doc is None else {folder / f for f in doc["files"]}


def foreign_files(target: Path) -> list[Path]:
    """Entries under ``target`` that no rtsgt manifest in it lists (sorted; symlinks count)."""
    owned: set[Path] = set()
    entries: list[Path] = []
    for root, dirs, files in os.walk(target, followlinks=False):
        here = Path(root)
        listed = _listed_files(here) if MANIFEST in files else None
        if listed is not None:
            owned |= listed
            owned.add(here / MANIFEST)
        # a symbolic link to a directory is an entry, not a place to descend into
        entries += [here / d for d in dirs if (here / d).is_symlink()]
        entries += [here / f for f in files]
    return sorted(p for p in entries if p not in owned)


def _contains(folder: Path, path: Path) -> bool:
    return path == folder or folder in path.parents


def check_target(target: str | os.PathLike, *, force: bool = False,
                 inputs: Iterable[str | os.PathLike] = ()) -> Path:
    """Check that ``target`` may receive a new output; returns its absolute path.

    Raises
    ------
    InputError
        ``target`` is a file; it is a non-empty directory and ``force`` is not given; with
        ``force``, it holds a file that rtsgt did not write, the current working directory or
        one of ``inputs``.
    """
    final = Path(os.path.abspath(target))
    if not final.exists() and not final.is_symlink():
        return final
    if final.is_symlink() or not final.is_dir():
        raise InputError("exists and is not a directory; give another output path", target)
    if not any(final.iterdir()):
        return final
    if not force:
        raise InputError("exists and is not empty; use --force to replace an earlier output "
                         "of rtsgt, or give another output path", target)
    resolved = final.resolve()
    cwd = Path.cwd().resolve()
    if _contains(resolved, cwd):
        raise InputError("holds the current working directory; --force will not replace it",
                         target)
    for p in inputs:
        if _contains(resolved, Path(p).resolve()):
            raise InputError(f"holds an input of this command ({p}); --force will not "
                             "replace it", target)
    foreign = foreign_files(final)
    if foreign:
        more = f" and {len(foreign) - 1} more" if len(foreign) > 1 else ""
        raise InputError(
            f"holds {foreign[0].relative_to(final).as_posix()}{more}, which rtsgt did not "
            "write; --force only replaces a directory that rtsgt wrote (remove it yourself, "
            "or give another output path)", target)
    return final


def check_output_file(path: str | os.PathLike, *, option: str,
                      written_by_rtsgt: Callable[[str], bool],
                      inputs: Iterable[str | os.PathLike] = ()) -> Path:
    """Check, before any work, that the file ``path`` (named by ``option``) may be written, and
    return it: not a directory, its directory existing, not one of ``inputs``, and if it exists
    an rtsgt output (``written_by_rtsgt`` judges its first 64 kB). Else
    :class:`~rtsgt.errors.InputError`."""
    out = Path(path)
    if out.is_dir():
        raise InputError(f"{option} names a directory; give a file name", out)
    parent = out.parent if str(out.parent) else Path(".")
    if not parent.is_dir():
        raise InputError(f"cannot write: the directory {parent} does not exist", out)
    if not out.exists() and not out.is_symlink():
        return out
    if any(out.resolve() == Path(p).resolve() for p in inputs):
        raise InputError(f"{option} names an input of this command; give another file name",
                         out)
    listed = _listed_files(parent.absolute())
    if not out.is_symlink() and out.is_file():
        if listed is not None and out.absolute() in listed:
            return out
        with open(out, "rb") as fh:
            head = fh.read(65536).decode("utf-8", errors="replace")
        if written_by_rtsgt(head):
            return out
    raise InputError(f"exists and is not an output of rtsgt; {option} will not replace it "
                     "(give another file name, or remove it yourself)", out)


def _manifest_text(folder: Path, kind: str) -> str:
    files = sorted(p.relative_to(folder).as_posix()
                   for p in folder.rglob("*") if not p.is_dir() or p.is_symlink())
    doc = {"written_by": "rtsgt", "version": __version__, "kind": kind,
           "files": [f for f in files if f != MANIFEST]}
    return json.dumps(doc, indent=1) + "\n"


def record_files(folder: str | os.PathLike, paths: Iterable[str | os.PathLike]) -> None:
    """Add files that rtsgt has written into the output ``folder`` to its manifest.

    Nothing is done when ``folder`` is not an rtsgt output (it has no manifest).
    """
    folder = Path(folder)
    doc = _manifest(folder)
    if doc is None:
        return
    names = set(doc["files"])
    names |= {Path(os.path.abspath(p)).relative_to(folder.absolute()).as_posix() for p in paths}
    doc["files"] = sorted(names)
    tmp = folder / f"{MANIFEST}.{secrets.token_hex(4)}.tmp"
    tmp.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, folder / MANIFEST)


def output_kind(folder: str | os.PathLike) -> str | None:
    """The kind of output (``"run"``, ``"batch"``, ...) of a directory rtsgt wrote, from its
    manifest; None if it has no valid manifest."""
    doc = _manifest(Path(folder))
    return None if doc is None else str(doc.get("kind"))


def complete_output(folder: str | os.PathLike, kind: str) -> bool:
    """Whether ``folder`` is a complete output of ``kind``: a directory with rtsgt's manifest
    of that kind, every file the manifest lists present (an output is put in place whole, so
    a file missing means one deleted since)."""
    folder = Path(folder)
    doc = _manifest(folder) if folder.is_dir() and not folder.is_symlink() else None
    if doc is None or doc.get("kind") != kind:
        return False
    return all((folder / f).is_file() for f in doc["files"])


def open_output_folder(target: str | os.PathLike, kind: str) -> Path:
    """A directory that rtsgt fills over several calls (``rtsgt batch``: one run directory
    per deployment, each put in place whole, and summary files): created with an empty
    manifest of ``kind`` if absent or empty; an earlier output of the same kind is reused as
    it is. Returns its absolute path.

    Raises
    ------
    InputError
        ``target`` is a file, or a non-empty directory that is not an output of ``kind``.
    """
    final = Path(os.path.abspath(target))
    if final.exists() or final.is_symlink():
        if final.is_symlink() or not final.is_dir():
            raise InputError("exists and is not a directory; give another output path", target)
        if any(final.iterdir()):
            if output_kind(final) != kind:
                raise InputError(f"exists and is not an output of rtsgt {kind}; give another "
                                 "output path (rtsgt never writes into a folder of yours)",
                                 target)
            return final
    try:
        final.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the output directory ({exc.strerror})",
                         target) from None
    tmp = final / f"{MANIFEST}.{secrets.token_hex(4)}.tmp"
    doc = {"written_by": "rtsgt", "version": __version__, "kind": kind, "files": []}
    tmp.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, final / MANIFEST)
    return final


class OutputDir:
    """Write a directory in one piece: ``with OutputDir(target, kind) as tmp: ...`` (``kind`` in the
    manifest; ``force`` replaces an earlier rtsgt output; ``inputs`` the target must not hold).
    The target is checked when made and before the finished directory replaces it; an
    exception removes the temporary directory and leaves the target as it was."""

    def __init__(self, target: str | os.PathLike, kind: str, *, force: bool = False,
                 inputs: Iterable[str | os.PathLike] = ()):
        self.target = target
        self.kind = kind
        self.force = force
        self.inputs = tuple(inputs)
        self.final = check_target(target, force=force, inputs=self.inputs)
        self.tmp: Path | None = None

    def __enter__(self) -> Path:
        parent = self.final.parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
            tmp = parent / f".{self.final.name}.rtsgt-tmp-{os.getpid()}-{secrets.token_hex(4)}"
            tmp.mkdir()  # mode 0777 less the umask, like any directory the user makes
        except OSError as exc:
            raise InputError(f"cannot create the output directory ({exc.strerror})",
                             self.target) from None
        self.tmp = tmp
        return tmp

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        tmp, self.tmp = self.tmp, None
        if tmp is None:
            return
        if exc_type is not None:
            shutil.rmtree(tmp, ignore_errors=True)
            return
        try:
            (tmp / MANIFEST).write_text(_manifest_text(tmp, self.kind), encoding="utf-8")
            check_target(self.target, force=self.force, inputs=self.inputs)
            if self.final.exists():
                old = self.final.with_name(
                    f".{self.final.name}.rtsgt-old-{os.getpid()}-{secrets.token_hex(4)}")
                os.replace(self.final, old)
                os.replace(tmp, self.final)
                shutil.rmtree(old, ignore_errors=True)
            else:
                os.replace(tmp, self.final)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
