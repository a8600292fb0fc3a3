"""Every file a scan names is read from inside the scan's own folder, or not at all.

A mesh file names other files: an OBJ its material library (trimesh takes the text after the first
`mtllib` anywhere in the file, comments and object names included), an MTL its texture maps, a glTF its
buffers and images, a PLY its `comment TextureFile`. trimesh's own FilePathResolver opens whatever
those names point at (absolute paths, `../` chains, symbolic links), so a hostile upload could make
the renderer read any image on the server. `ConfinedResolver` is the resolver every `trimesh.load` of
a scan gets instead: it serves a name only when its real path (symbolic links followed) lies inside
the folder of the mesh's real path, refuses everything else before opening it, and remembers what it
refused so the loader can turn that into a clear message. `read_confined` applies the same rule to the
files our own code reads beside a mesh (label files, material libraries in the pre-checks).

The root is always the folder holding the mesh file, whatever entry point loaded it (an upload's
extraction folder, a registered folder, `omnidata plan/generate` arguments, the worker's cache of the
stored space), so a scan accepted at upload is confined the same way when it is planned and rendered.
"""

from __future__ import annotations

import os
import re
import stat
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from urllib.parse import unquote

from trimesh.resolvers import Resolver

from services.core.ingest.guard.texture_limits import texture_refusal

_URL_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]+:")  # file:, http:, ... (one letter would be a drive)
_DRIVE = re.compile(r"^[A-Za-z]:")


class ReferenceRefused(PermissionError):
    """A file named by a scan that lies outside the scan's folder (or is over a limit); never opened.

    An OSError on purpose: trimesh's loaders treat it like a missing file and carry on, and the loader
    reports the refusal it recorded once trimesh returns.
    """


def real_folder(mesh: str | Path) -> Path:
    """The folder holding the real file of `mesh` (symbolic links followed): the root of its references."""
    return Path(os.path.realpath(mesh)).parent


def is_inside(path: str | Path, root: Path) -> bool:
    """Whether the real path of `path` is `root` or below it (`root` itself already real)."""
    real = os.path.realpath(path)
    return real == str(root) or real.startswith(str(root).rstrip("/") + "/")


def read_confined(path: str | Path, mesh: str | Path) -> bytes:
    """The bytes of `path`, a file beside `mesh`; ReferenceRefused when its real path leaves mesh's folder."""
    root = real_folder(mesh)
    if not is_inside(path, root):
        raise ReferenceRefused(
            f"{Path(path).name!r} is a symbolic link out of the scan's folder; refusing to read it"
        )
    return _read_regular(Path(os.path.realpath(path)))


def _read_regular(real: Path) -> bytes:
    """Read a regular file by its real path; no link is followed and a FIFO or device never blocks us."""
    fd = os.open(real, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise ReferenceRefused(f"{real.name!r} is not a regular file")
        with os.fdopen(fd, "rb", closefd=False) as f:
            return f.read()
    finally:
        os.close(fd)


@dataclass
class ResolverLog:
    """What a resolver (and the resolvers it namespaced) served and refused, in order."""

    served: list[Path] = field(default_factory=list)
    refused: list[str] = field(default_factory=list)


class ConfinedResolver(Resolver):
    """trimesh resolver serving files from the folder of `mesh` (its real path) and nothing outside it."""

    def __init__(self, mesh: str | Path, *, parent: str | Path | None = None, log: ResolverLog | None = None):
        self.root = real_folder(mesh)
        # `parent` and `file_name` are what trimesh's loaders read off a resolver (names for materials)
        self.parent = str(parent if parent is not None else self.root)
        self.file_name = Path(mesh).name
        self.log = log if log is not None else ResolverLog()

    # -------------------------------------------------------------------------------- trimesh's API
    def get(self, name: str) -> bytes:
        """The bytes of the file `name` (relative to the mesh); ReferenceRefused or FileNotFoundError."""
        real = self._locate(str(name))
        data = _read_regular(real)
        problem = texture_refusal(real.name, data)
        if problem is not None:
            self._refuse(problem)
        self.log.served.append(real)
        return data

    def namespaced(self, namespace: str) -> ConfinedResolver:
        """A resolver for a sub-folder, confined to the same root and sharing the log."""
        sub = Path(self.parent) / namespace
        if not is_inside(sub, self.root):
            self._refuse(f"{namespace!r} names a folder outside the scan's folder")
        resolver = ConfinedResolver(Path(self.parent) / self.file_name, parent=sub, log=self.log)
        resolver.root = self.root
        return resolver

    def keys(self) -> Iterator[str]:
        """Names of the regular files under the root (links are not followed)."""
        for folder, _dirs, names in os.walk(self.root):
            rel = os.path.relpath(folder, self.root)
            for name in names:
                if os.path.isfile(os.path.join(folder, name)) and is_inside(
                    os.path.join(folder, name), self.root
                ):
                    yield name if rel == "." else f"{rel}/{name}"

    def write(self, name: str, data: str | bytes) -> None:
        """Loading never writes: refused."""
        raise PermissionError(f"writing {name!r} beside an uploaded scan is not allowed")

    # -------------------------------------------------------------------------------- ours
    def refusal(self) -> str | None:
        """The first refusal, as a message for the user, or None when every name was inside."""
        return self.log.refused[0] if self.log.refused else None

    def _refuse(self, message: str) -> None:
        self.log.refused.append(message)
        raise ReferenceRefused(message)

    def _locate(self, name: str) -> Path:
        raw = name.strip()
        decoded = unquote(raw)  # glTF URIs are percent-encoded; a %2e%2e/ is still '..'
        for candidate in dict.fromkeys((raw, decoded)):
            clean = candidate.replace("\\", "/")
            if clean.startswith("/") or _DRIVE.match(clean) or _URL_SCHEME.match(clean):
                self._refuse(
                    f"names the file {raw!r} by an absolute path or URL; name files relative to "
                    "the mesh and include them"
                )
            # as named, then its bare file name beside the mesh (what trimesh's own resolver falls back to)
            for rel in dict.fromkeys((clean, PurePosixPath(clean).name)):
                if not rel:
                    continue
                path = Path(self.parent) / rel
                if not is_inside(path, self.root):
                    how = (
                        "which climbs out of"
                        if ".." in PurePosixPath(rel).parts
                        else "a symbolic link out of"
                    )
                    self._refuse(f"names the file {raw!r}, {how} the scan's folder; refusing to read it")
                real = Path(os.path.realpath(path))
                if real.is_file():
                    return real
        raise FileNotFoundError(raw)
