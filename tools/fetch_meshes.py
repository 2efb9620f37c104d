"""Fetch the real meshes the mesh tests use into tests/data/meshes/ (never committed).

Every file comes out of a published package, fetched by name and exact version through the
ordinary clients (``npm pack``, ``pip download``), and is checked against its SHA-256:

``bunny.obj``
    The Stanford bunny of the npm package ``bunny@1.0.1`` (public domain): its ``index.js``
    (``exports.positions=[[x,y,z],...]`` and ``exports.cells=[[i,j,k],...]``) written as an
    OBJ. Watertight, one body, 1839 vertices, about 10 units across.
``nut.ply``
    A hex nut from the pyvista wheel (``pyvista/examples/nut.ply``): a CAD part with sharp
    edges, watertight, one body, genus 1, 523 vertices, about 46 units across.
``ant.ply``
    From the same wheel: 15 separate closed bodies (the several-bodies error).
``StanfordBunny.ply``
    The open scan of the bunny from the pymeshfix wheel (``pymeshfix/examples/``): holes and
    non-manifold edges (the not-closed error).

Usage::

    python tools/fetch_meshes.py [--dest DIR]

Idempotent: a file already in the folder is left alone (delete it to fetch it again). Exits 0
when every file is there, 1 with one line per failure on stderr otherwise. Needs ``npm`` on the
PATH and pip in the running interpreter (``make meshes`` runs it with the project's venv).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import subprocess
import sys
import tarfile
import tempfile
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

#: The default destination: tests/data/meshes/ of this checkout.
DEST = Path(__file__).resolve().parent.parent / "tests" / "data" / "meshes"

#: The pinned packages.
BUNNY_NPM = "bunny@1.0.1"
PYVISTA_WHEEL = "pyvista==0.49.1"
PYMESHFIX_WHEEL = "pymeshfix==0.18.1"

#: pymeshfix ships binary wheels only; this one is asked for whatever the machine, so the
#: file and its checksum are the same everywhere (only its data file is used).
_PYMESHFIX_PLATFORM = (
    "--platform",
    "manylinux_2_28_x86_64",
    "--python-version",
    "3.11",
    "--implementation",
    "cp",
    "--abi",
    "cp311",
)


class FetchError(RuntimeError):
    """One file could not be fetched; the message says which and why."""


@dataclass(frozen=True)
class Source:
    """One output file: which package holds it, where inside, and its checksum."""

    name: str  # file written in the destination
    package: str  # npm spec or pip requirement
    member: str  # path inside the package archive
    sha256: str  # of the member as published
    convert: Callable[[bytes], bytes] | None = None  # member -> file written


def bunny_js_to_obj(data: bytes) -> bytes:
    """The bunny package's ``index.js`` as an OBJ file (1-based faces, same vertex order).

    Raises
    ------
    FetchError
        The text is not ``exports.positions=[...]`` then ``exports.cells=[...]``, or indexes
        a vertex that does not exist.
    """
    text = data.decode("utf-8")
    match = re.fullmatch(
        r"\s*exports\.positions\s*=\s*(\[.*?\])\s*;?\s*exports\.cells\s*=\s*(\[.*\])\s*;?\s*",
        text,
        flags=re.DOTALL,
    )
    if match is None:
        raise FetchError("bunny index.js: not exports.positions=[...] then exports.cells=[...]")
    positions = json.loads(match.group(1))
    cells = json.loads(match.group(2))
    n = len(positions)
    if not all(len(p) == 3 for p in positions) or not all(
        len(c) == 3 and all(0 <= i < n for i in c) for c in cells
    ):
        raise FetchError("bunny index.js: positions or cells are not triangles of known vertices")
    lines = [f"# Stanford bunny from the npm package {BUNNY_NPM} (public domain)"]
    lines += [f"v {x!r} {y!r} {z!r}" for x, y, z in positions]
    lines += [f"f {i + 1} {j + 1} {k + 1}" for i, j, k in cells]
    return ("\n".join(lines) + "\n").encode("ascii")


SOURCES = (
    Source(
        "bunny.obj",
        BUNNY_NPM,
        "package/index.js",
        "4c428649f2cabf3c11a0225f58367c503d181b7e2a59223a610c88a5308412b3",
        bunny_js_to_obj,
    ),
    Source(
        "nut.ply",
        PYVISTA_WHEEL,
        "pyvista/examples/nut.ply",
        "51df5ca42ddbac9123e59678d532557278b11dee915274c98ea8897acc604c0a",
    ),
    Source(
        "ant.ply",
        PYVISTA_WHEEL,
        "pyvista/examples/ant.ply",
        "1e825c23c85588c9ea8d31b53e09791a6cd20fa9f835e98d4c61389e4209a73b",
    ),
    Source(
        "StanfordBunny.ply",
        PYMESHFIX_WHEEL,
        "pymeshfix/examples/StanfordBunny.ply",
        "04ade0928afe3f307851bcb7fa932d6f9375d7dff8432615c8105828209deb3f",
    ),
)


def _run(cmd: list[str], cwd: Path) -> None:
    """Run a package client; FetchError with its last lines of output when it fails."""
    try:
        res = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=600)
    except FileNotFoundError:
        raise FetchError(f"{cmd[0]} is not installed (needed for {' '.join(cmd)})") from None
    except subprocess.TimeoutExpired:
        raise FetchError(f"{' '.join(cmd)} did not finish within 600 s") from None
    if res.returncode != 0:
        tail = " | ".join((res.stderr or res.stdout).strip().splitlines()[-3:])
        raise FetchError(f"{' '.join(cmd)} failed (exit {res.returncode}): {tail}")


def _only(folder: Path, pattern: str, what: str) -> Path:
    found = sorted(folder.glob(pattern))
    if len(found) != 1:
        raise FetchError(f"{what}: expected one {pattern} in the download, found {len(found)}")
    return found[0]


def _npm_members(spec: str, members: list[str], work: Path) -> dict[str, bytes]:
    """``npm pack SPEC`` and the named files of its tarball."""
    _run(["npm", "pack", "--silent", spec], work)
    tgz = _only(work, "*.tgz", f"npm pack {spec}")
    out: dict[str, bytes] = {}
    with tarfile.open(tgz, "r:gz") as tar:
        for member in members:
            try:
                fh = tar.extractfile(member)
            except KeyError:
                fh = None
            if fh is None:
                raise FetchError(f"{spec}: the package has no file {member}")
            out[member] = fh.read()
    return out


def _pip_members(spec: str, members: list[str], work: Path) -> dict[str, bytes]:
    """``pip download --no-deps SPEC`` (a wheel) and the named files inside it."""
    extra = _PYMESHFIX_PLATFORM if spec == PYMESHFIX_WHEEL else ()
    _run(
        [
            sys.executable,
            "-m",
            "pip",
            "download",
            "--quiet",
            "--disable-pip-version-check",
            "--no-deps",
            "--only-binary=:all:",
            *extra,
            "--dest",
            str(work),
            spec,
        ],  # fmt: skip
        work,
    )
    wheel = _only(work, "*.whl", f"pip download {spec}")
    out: dict[str, bytes] = {}
    with zipfile.ZipFile(wheel) as zf:
        for member in members:
            try:
                out[member] = zf.read(member)
            except KeyError:
                raise FetchError(f"{spec}: the wheel has no file {member}") from None
    return out


def fetch(dest: Path = DEST, log: Callable[[str], None] = print) -> list[str]:
    """Write every missing file of :data:`SOURCES` into ``dest``.

    Parameters
    ----------
    dest : pathlib.Path
        Destination folder, created if missing.
    log : callable
        Receives one line per file fetched or already there.

    Returns
    -------
    list of str
        One message per file that could not be fetched (empty: all there).
    """
    dest.mkdir(parents=True, exist_ok=True)
    errors: list[str] = []
    by_package: dict[str, list[Source]] = {}
    for src in SOURCES:
        if (dest / src.name).is_file():
            log(f"{src.name}: already there")
        else:
            by_package.setdefault(src.package, []).append(src)
    for package, wanted in by_package.items():
        try:
            with tempfile.TemporaryDirectory(prefix="fetch-meshes-") as tmp:
                get = _npm_members if package == BUNNY_NPM else _pip_members
                data = get(package, [s.member for s in wanted], Path(tmp))
        except (FetchError, OSError, tarfile.TarError, zipfile.BadZipFile) as exc:
            errors += [f"{s.name}: cannot fetch {package}: {exc}" for s in wanted]
            continue
        for src in wanted:
            raw = data[src.member]
            digest = hashlib.sha256(raw).hexdigest()
            if digest != src.sha256:
                errors.append(
                    f"{src.name}: {package} {src.member} has SHA-256 {digest}, "
                    f"expected {src.sha256}"
                )
                continue
            try:
                body = src.convert(raw) if src.convert is not None else raw
                part = dest / f".{src.name}.part"
                part.write_bytes(body)
                os.replace(part, dest / src.name)
            except (FetchError, OSError, ValueError) as exc:
                errors.append(f"{src.name}: {exc}")
                continue
            log(f"{src.name}: fetched from {package} ({len(body)} bytes)")
    return errors


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--dest", type=Path, default=DEST, help="destination folder")
    args = parser.parse_args(argv)
    errors = fetch(args.dest)
    for line in errors:
        print(f"fetch_meshes: error: {line}", file=sys.stderr)
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
