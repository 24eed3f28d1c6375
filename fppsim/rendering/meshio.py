"""Mesh formats trimesh does not read: PLY made of triangle strips (``element tristrips``).

Scanner software (e.g. Stanford's range-scan tools) writes surfaces as one ``tristrips`` element with a
list property ``vertex_indices``: strips separated by -1. trimesh ignores that element and reports an
empty mesh, so :func:`read_ply_tristrips` parses the PLY itself (ascii, binary little/big endian) and
:func:`strips_to_triangles` turns strips into triangles with consistent winding.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from fppsim.errors import PlyError

__all__ = ["PlyError", "ply_has_tristrips", "read_ply_tristrips", "strips_to_triangles"]

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _header(data: bytes, path) -> tuple[str, list, int]:
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise PlyError(f"{path}: not a PLY file (no 'ply' ... 'end_header')")
    nl = data.find(b"\n", end)
    body = nl + 1 if nl >= 0 else len(data)
    fmt, elements = None, []
    for raw in data[:end].decode("ascii", errors="replace").splitlines():
        t = raw.split()
        if not t or t[0] in ("ply", "comment", "obj_info"):
            continue
        if t[0] == "format":
            fmt = t[1]
        elif t[0] == "element" and len(t) == 3:
            elements.append({"name": t[1], "count": int(t[2]), "props": []})
        elif t[0] == "property" and elements:
            if t[1] == "list" and len(t) == 5:
                elements[-1]["props"].append((t[4], "list", _PLY_TYPES.get(t[2]), _PLY_TYPES.get(t[3])))
            elif len(t) == 3:
                elements[-1]["props"].append((t[2], "scalar", _PLY_TYPES.get(t[1]), None))
            else:
                raise PlyError(f"{path}: malformed header line {raw!r}")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise PlyError(f"{path}: unknown PLY format {fmt!r}")
    for el in elements:
        for name, kind, t1, t2 in el["props"]:
            if t1 is None or (kind == "list" and t2 is None):
                raise PlyError(f"{path}: property {name} of element {el['name']} has an unknown type")
    return fmt, elements, body


def ply_has_tristrips(path: str | os.PathLike) -> bool:
    """True when the PLY header declares a non-empty ``tristrips`` element."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(65536)
        _, elements, _ = _header(head, path)
    except (OSError, PlyError, ValueError):
        return False
    return any(el["name"] == "tristrips" and el["count"] > 0 for el in elements)


def strips_to_triangles(strips: np.ndarray) -> np.ndarray:
    """(M,) int vertex indices of triangle strips separated by -1 -> (F, 3) int64 triangles.

    Triangle k of a strip is (s[k], s[k+1], s[k+2]) for even k and (s[k+1], s[k], s[k+2]) for odd k,
    so all keep the strip's winding; degenerate triangles (a repeated index, used to join strips) are
    dropped.
    """
    s = np.asarray(strips, dtype=np.int64).ravel()
    tris = []
    cuts = np.flatnonzero(s < 0)
    start = 0
    for stop in list(cuts) + [len(s)]:
        run = s[start:stop]
        start = stop + 1
        if len(run) < 3:
            continue
        a, b, c = run[:-2], run[1:-1], run[2:]
        odd = (np.arange(len(a)) % 2) == 1
        t = np.stack([np.where(odd, b, a), np.where(odd, a, b), c], axis=1)
        tris.append(t)
    if not tris:
        return np.zeros((0, 3), np.int64)
    t = np.concatenate(tris)
    keep = (t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])
    return t[keep]


def read_ply_tristrips(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) float64 and triangles (F, 3) int64 of a PLY whose faces are triangle strips
    (a ``face`` element, when present too, is added as well; polygons are fanned)."""
    path = Path(path)
    data = path.read_bytes()
    fmt, elements, pos = _header(data, path)
    endian = ">" if fmt == "binary_big_endian" else "<"
    tokens = data[pos:].split() if fmt == "ascii" else None
    ti = 0
    out: dict[str, dict] = {}
    try:
        for el in elements:
            props, n = el["props"], el["count"]
            cols: dict[str, list] = {p[0]: [] for p in props}
            if fmt == "ascii":
                for _ in range(n):
                    for name, kind, t1, t2 in props:
                        if kind == "scalar":
                            cols[name].append(float(tokens[ti]))
                            ti += 1
                        else:
                            k = int(tokens[ti])
                            cols[name].append(np.array(tokens[ti + 1: ti + 1 + k], dtype=np.float64).astype(np.int64))
                            ti += 1 + k
            elif all(kind == "scalar" for _, kind, _, _ in props):  # fixed-size rows: one vectorised read
                dt = np.dtype([(name, endian + t1) for name, _, t1, _ in props])
                rows = np.frombuffer(data, dtype=dt, count=n, offset=pos)
                pos += dt.itemsize * n
                cols = {name: rows[name] for name in rows.dtype.names}
            else:
                for _ in range(n):
                    for name, kind, t1, t2 in props:
                        if kind == "scalar":
                            d = np.dtype(endian + t1)
                            cols[name].append(np.frombuffer(data, d, 1, pos)[0])
                            pos += d.itemsize
                        else:
                            dc, di = np.dtype(endian + t1), np.dtype(endian + t2)
                            k = int(np.frombuffer(data, dc, 1, pos)[0])
                            pos += dc.itemsize
                            cols[name].append(np.frombuffer(data, di, k, pos).astype(np.int64))
                            pos += di.itemsize * k
            out[el["name"]] = cols
    except (IndexError, ValueError) as exc:
        raise PlyError(f"{path}: truncated or malformed PLY body ({exc})") from None
    vert = out.get("vertex")
    if not vert or not all(k in vert for k in ("x", "y", "z")):
        raise PlyError(f"{path}: no vertex element with x, y, z")
    V = np.stack([np.asarray(vert[k], dtype=np.float64) for k in ("x", "y", "z")], axis=1)
    faces = []
    for cols in [out.get("tristrips", {})]:
        for key in ("vertex_indices", "vertex_index"):
            for strip in cols.get(key, []):
                faces.append(strips_to_triangles(strip))
    for key in ("vertex_indices", "vertex_index"):
        for poly in out.get("face", {}).get(key, []):
            poly = np.asarray(poly, dtype=np.int64)
            if len(poly) >= 3:
                faces.append(np.stack([np.full(len(poly) - 2, poly[0]), poly[1:-1], poly[2:]], axis=1))
    F = np.concatenate(faces) if faces else np.zeros((0, 3), np.int64)
    return V, F
