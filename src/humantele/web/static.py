"""The pages' own files (``GET /web/...``), for both daemons' web servers.

Only the files that were in the page's directory when the server started are served, looked up
by name in a table: any other name (too long for the file system, ``..``, ``//``, a NUL, a
directory, a symlink, a hidden file) is a plain 404, never an exception in the server or a
file outside the directory. aiohttp's own ``add_static`` stats whatever path it is given, so a
5000-character name gave a 500 with an ENAMETOOLONG traceback.
"""

from __future__ import annotations

from pathlib import Path

from aiohttp import web

MAX_NAME = 255  # characters in a requested name (the longest served is ~40)


def page_files(directory: str | Path) -> dict[str, Path]:
    """``relative/posix/name -> path`` of each regular file under ``directory`` (symlinks,
    hidden files and ``__pycache__`` left out)."""
    root = Path(directory)
    files: dict[str, Path] = {}
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root)
        if any(p.startswith(".") or p == "__pycache__" for p in rel.parts):
            continue
        if path.is_symlink() or not path.is_file():
            continue
        files[rel.as_posix()] = path
    return files


def add_page_files(app: web.Application, directory: str | Path, prefix: str = "/web/") -> None:
    """Serve the files of ``directory`` under ``prefix`` (GET and HEAD); 404 for any other."""
    files = page_files(directory)

    async def handler(request: web.Request) -> web.StreamResponse:
        name = request.match_info["name"]
        path = files.get(name) if len(name) <= MAX_NAME else None
        if path is None:
            raise web.HTTPNotFound()
        return web.FileResponse(path)

    app.router.add_get(prefix + "{name:.+}", handler)
