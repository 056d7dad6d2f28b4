"""Coloured point clouds as PLY: a binary little-endian writer any viewer opens, and a reader.

The writer emits the most widely supported vertex layout: ``float x, y, z`` (+ optional ``float
nx, ny, nz``) + ``uchar red, green, blue``. The reader parses any ``binary_little_endian`` or
``ascii`` PLY whose first element is ``vertex`` with scalar properties (used by tests and tools).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["write_ply", "write_ply_vertices", "read_ply", "PlyError"]

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


class PlyError(ValueError):
    """Malformed PLY input or invalid arrays to write; the message names the file."""


def write_ply(
    path: str | Path,
    points: np.ndarray,
    colors: np.ndarray | None = None,
    normals: np.ndarray | None = None,
    *,
    comment: str | None = None,
) -> Path:
    """Write points (N, 3) with optional colours (N, 3) uint8 and normals (N, 3) atomically.

    Coordinates are stored as float32. Non-finite points are rejected (viewers choke on them).
    """
    path = Path(path)
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise PlyError(f"{path}: points must be (N, 3), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise PlyError(f"{path}: points contain non-finite values (inf/NaN)")
    n = pts.shape[0]
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if normals is not None:
        nrm = np.asarray(normals)
        if nrm.shape != (n, 3) or not np.all(np.isfinite(nrm)):
            raise PlyError(f"{path}: normals must be finite (N, 3) = ({n}, 3), got {nrm.shape}")
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if colors is not None:
        col = np.asarray(colors)
        if col.shape != (n, 3) or col.dtype != np.uint8:
            raise PlyError(f"{path}: colours must be (N, 3) = ({n}, 3) uint8, got {col.shape} {col.dtype}")
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    data = np.empty(n, dtype=np.dtype(fields))
    data["x"], data["y"], data["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if normals is not None:
        data["nx"], data["ny"], data["nz"] = nrm[:, 0], nrm[:, 1], nrm[:, 2]
    if colors is not None:
        data["red"], data["green"], data["blue"] = col[:, 0], col[:, 1], col[:, 2]
    return write_ply_vertices(path, data, comment=comment)


_PLY_NAME_OF = {
    "f4": "float",
    "f8": "double",
    "u1": "uchar",
    "i1": "char",
    "u2": "ushort",
    "i2": "short",
    "u4": "uint",
    "i4": "int",
}
"""PLY property type of each little-endian numpy scalar type."""


def write_ply_vertices(path: str | Path, vertices: np.ndarray, *, comment: str | None = None) -> Path:
    """Write a structured array as the ``vertex`` element of a binary little-endian PLY, atomically.

    Property names and types come from the array's fields (any scalar type in the PLY spec); the one
    writer behind :func:`write_ply` and the 3DGS scene writer.
    """
    from image2sim.simulator.io.atomic import atomic_open

    path = Path(path)
    if vertices.dtype.names is None:
        raise PlyError(f"{path}: vertices must be a structured array, got dtype {vertices.dtype}")
    header = ["ply", "format binary_little_endian 1.0"]
    if comment:
        header += [f"comment {line}" for line in comment.splitlines()]
    header.append(f"element vertex {vertices.shape[0]}")
    for name in vertices.dtype.names:
        scalar = vertices.dtype.fields[name][0]
        key = scalar.newbyteorder("<").str.lstrip("<|")
        if key not in _PLY_NAME_OF or scalar.shape:
            raise PlyError(f"{path}: field {name!r} has type {scalar} which PLY cannot store")
        header.append(f"property {_PLY_NAME_OF[key]} {name}")
    header.append("end_header")
    data = vertices.astype(vertices.dtype.newbyteorder("<"), copy=False)
    with atomic_open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(np.ascontiguousarray(data).tobytes())
    return path


def read_ply(path: str | Path) -> dict[str, np.ndarray]:
    """Read the vertex element of a PLY file: ``{"points": (N, 3) float64, "colors"?, "normals"?, <props>}``.

    Every scalar vertex property is also returned under its own name.
    """
    path = Path(path)
    if not path.is_file():
        raise PlyError(f"{path}: missing PLY file")
    raw = path.read_bytes()
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise PlyError(f"{path}: not a PLY file (no 'ply' magic or no end_header)")
    body_start = raw.index(b"\n", end) + 1
    lines = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt, count, props, element = None, None, [], None
    for line in lines[1:]:
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            fmt = tok[1]
        elif tok[0] == "element":
            element = tok[1]
            if element == "vertex":
                count = int(tok[2])
            elif count is not None:
                break  # only the vertex element (first) is read
        elif tok[0] == "property" and element == "vertex":
            if tok[1] == "list":
                raise PlyError(f"{path}: list properties in the vertex element are not supported")
            if tok[1] not in _PLY_TYPES:
                raise PlyError(f"{path}: unknown property type {tok[1]!r}")
            props.append((tok[2], _PLY_TYPES[tok[1]]))
    if count is None or not props:
        raise PlyError(f"{path}: no vertex element with properties")
    if fmt == "binary_little_endian":
        dtype = np.dtype([(n, "<" + t) for n, t in props])
        need = dtype.itemsize * count
        if len(raw) - body_start < need:
            raise PlyError(f"{path}: truncated: {len(raw) - body_start} data bytes, header promises {need}")
        data = np.frombuffer(raw, dtype=dtype, count=count, offset=body_start)
        cols = {n: np.asarray(data[n]) for n, _ in props}
    elif fmt == "ascii":
        rows = raw[body_start:].decode("ascii").split("\n")[:count]
        table = np.array([r.split()[: len(props)] for r in rows], dtype=np.float64).reshape(count, len(props))
        cols = {n: table[:, i].astype(t) for i, (n, t) in enumerate(props)}
    else:
        raise PlyError(f"{path}: unsupported PLY format {fmt!r}")
    out: dict[str, np.ndarray] = dict(cols)
    try:
        out["points"] = np.stack([cols["x"], cols["y"], cols["z"]], axis=1).astype(np.float64)
    except KeyError:
        raise PlyError(f"{path}: vertex element lacks x/y/z") from None
    if all(c in cols for c in ("red", "green", "blue")):
        out["colors"] = np.stack([cols["red"], cols["green"], cols["blue"]], axis=1).astype(np.uint8)
    if all(c in cols for c in ("nx", "ny", "nz")):
        out["normals"] = np.stack([cols["nx"], cols["ny"], cols["nz"]], axis=1).astype(np.float64)
    return out
